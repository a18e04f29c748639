"""Resident memory and CPU time of running processes, read from /proc on a thread.

For the reliability tests (is the relay's memory bounded on a bad link, the host's flat behind
a slow output?) and benchmarks/soak.py. Linux only, as /proc is.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

TICKS_PER_S = os.sysconf("SC_CLK_TCK")


@dataclass(frozen=True, slots=True)
class Sample:
    at: float
    """time.monotonic() of the reading."""
    rss_mb: float
    cpu_s: float
    """User + system CPU seconds used so far."""


def read(pid: int) -> Sample | None:
    """One reading of ``pid``; None once it has ended."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
        stat = Path(f"/proc/{pid}/stat").read_text()
    except (FileNotFoundError, ProcessLookupError):
        return None
    rss_kb = next((int(line.split()[1]) for line in status.splitlines()
                   if line.startswith("VmRSS:")), 0)
    # Fields after the command name (which may hold spaces) start at field 3 (state).
    fields = stat.rsplit(")", 1)[1].split()
    cpu_ticks = int(fields[11]) + int(fields[12])  # utime, stime: fields 14 and 15
    return Sample(time.monotonic(), rss_kb / 1024, cpu_ticks / TICKS_PER_S)


@dataclass
class Sampler:
    """Samples ``pid`` every ``period_s`` until :meth:`stop` (or its end)."""

    pid: int
    period_s: float = 0.2
    samples: list[Sample] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"sample-{self.pid}", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while True:
            sample = read(self.pid)
            if sample is None:
                return
            self.samples.append(sample)
            if self._stop.wait(self.period_s):
                return

    def stop(self) -> list[Sample]:
        self._stop.set()
        self._thread.join(timeout=5.0)
        return self.samples

    def between(self, start: float, end: float) -> list[Sample]:
        return [s for s in self.samples if start <= s.at <= end]

    def peak_mb(self, start: float = 0.0, end: float = float("inf")) -> float:
        return max((s.rss_mb for s in self.between(start, end)), default=0.0)

    def cpu_percent(self, start: float = 0.0, end: float = float("inf")) -> float:
        """Mean CPU use between the first and last sample in [start, end], in % of one core."""
        window = self.between(start, end)
        if len(window) < 2 or window[-1].at <= window[0].at:
            return 0.0
        return 100 * (window[-1].cpu_s - window[0].cpu_s) / (window[-1].at - window[0].at)
