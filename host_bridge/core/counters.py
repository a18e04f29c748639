"""What the host counts per topic (received, converted, dropped, skipped, warnings, wire
sequence gaps, conversion time) and the table it prints when it stops; the /_stats series
(stats.py) count gaps the same way."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt


@dataclass(slots=True)
class TopicCounters:
    msgtype: str
    received: int = 0
    converted: int = 0
    dropped: int = 0
    # Disabled in the host config: counted, never decoded.
    skipped: int = 0
    warnings: int = 0
    sequence_gaps: int = 0
    last_sequence: int | None = None
    convert_seconds: float = 0.0

    def receive(
        self, count: int, sequence: npt.NDArray[np.int64] | Sequence[int | None] | None
    ) -> None:
        """``count`` messages arrived, carrying the wire sequence numbers ``sequence`` (None, or
        None for a message: a source without them, a bag): the numbers lost since the last one
        are counted as gaps."""
        self.received += count
        if sequence is None:
            return
        if isinstance(sequence, np.ndarray):
            self.sequence_gaps += sequence_gaps(self.last_sequence, sequence)
            if len(sequence):
                self.last_sequence = int(sequence[-1])
            return
        for number in sequence:
            if number is not None:
                self.sequence_gaps += sequence_gap(self.last_sequence, number)
                self.last_sequence = number


def sequence_gap(last: int | None, sequence: int) -> int:
    """Messages lost between two wire sequence numbers (u32, wrapping)."""
    if last is None:
        return 0
    gap = (sequence - last - 1) & 0xFFFFFFFF
    # A relay restart starts again at 0; that is not a loss.
    return gap if 0 < gap < 0x80000000 and sequence != 0 else 0


SHORT_RUN = 16
"""Runs shorter than this are summed in Python: numpy's calls cost a run of one 20-25 us, the
loop 0.5 (a live host's runs are mostly a few messages; 25 robots' make thousands a second)."""


def sequence_gaps(last: int | None, sequence: npt.NDArray[np.int64]) -> int:
    """:func:`sequence_gap` summed over a run's sequence numbers, ``last`` before the first."""
    if len(sequence) < SHORT_RUN:
        total = 0
        for number in sequence.tolist():
            total += sequence_gap(last, number)
            last = number
        return total
    before = np.concatenate([[-1 if last is None else last], sequence[:-1]])
    gaps = (sequence - before - 1) & 0xFFFFFFFF
    counted = (gaps > 0) & (gaps < 0x80000000) & (sequence != 0)
    if last is None:
        counted[0] = False
    return int(gaps[counted].sum())


def summary_table(counters: Mapping[tuple[str, str], TopicCounters]) -> str:
    """A table of every topic seen: type, received, converted, dropped, warnings, wire
    sequence gaps and mean conversion time, with a total row."""
    header = ("robot", "topic", "type", "received", "converted", "dropped", "warnings", "gaps",
              "ms/msg")
    ordered = sorted(counters.items())
    every = [c for _, c in ordered]
    total = TopicCounters(
        "",
        received=sum(c.received for c in every),
        converted=sum(c.converted for c in every),
        dropped=sum(c.dropped for c in every),
        warnings=sum(c.warnings for c in every),
        sequence_gaps=sum(c.sequence_gaps for c in every),
        convert_seconds=sum(c.convert_seconds for c in every),
    )
    rows = [header] + [
        (robot, topic, c.msgtype, str(c.received), str(c.converted), str(c.dropped),
         str(c.warnings), str(c.sequence_gaps),
         f"{c.convert_seconds * 1000 / c.converted:.3f}" if c.converted else "-")
        for (robot, topic), c in [*ordered, (("total", f"{len(ordered)} topics"), total)]
    ]
    widths = [max(len(r[i]) for r in rows) for i in range(len(header))]
    return "\n".join(
        "  ".join(cell.ljust(w) for cell, w in zip(r, widths, strict=True)).rstrip() for r in rows
    )
