"""Which robots one of a live host's worker processes converts (``swanky-host --workers N``).

One host process converts about one core's worth of messages, however many cores the PC has:
its Python runs under one GIL, and with 25 demo robots a third of its CPU went to the kernel
handing that lock between its threads (``perf``, benchmarks/RESULTS.md). ``--workers N`` runs
N processes, each converting the robots of its shard: a robot belongs to shard
``crc32(name) % N``, which every worker computes alone (no coordination, and a robot that
reconnects comes back to the same worker). crc32 spreads the demo's sim, sim2, ... sim25 13 and
12 over two workers.
"""

from __future__ import annotations

import zlib
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Shard:
    """Worker ``index`` of ``count``: the robots it converts."""

    index: int
    count: int

    def owns(self, robot: str) -> bool:
        return zlib.crc32(robot.encode()) % self.count == self.index

    @property
    def name(self) -> str:
        """How the worker is named where several share a viewer (its viewer lag, its files)."""
        return f"worker{self.index}"
