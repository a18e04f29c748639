"""Where a recording goes (``--spawn``, ``--rerun-addr``, ``--save``, ``--serve-web``), as a
record :mod:`host_bridge.cli` fills without importing Rerun: ``swanky-host --help`` must not pay
for loading the SDK. :mod:`host_bridge.outputs.sink` opens what it names."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

LOOPBACK = "127.0.0.1"
SAVE_SPLIT_S = 120.0
"""How long a live ``--save`` file runs before the next one starts (``--save-split``): Rerun
keeps the index it ends a file with in memory until then (:class:`host_bridge.outputs.sink.SavedFile`)."""


@dataclass(frozen=True, slots=True)
class SinkOptions:
    """Where the recording goes; several at once are allowed (e.g. a viewer and a file)."""

    spawn: bool = False
    connect: str | None = None
    save: Path | None = None
    serve_web: bool = False
    web_port: int | None = None
    grpc_port: int | None = None
    web_bind: str = LOOPBACK
    """Address the ``--serve-web`` gRPC server (the recording itself) listens on."""
    recording_id: str | None = None
    save_split_s: float | None = None
    """Start a new ``save`` file every this many seconds (a live host's); None: one file."""

    @property
    def any(self) -> bool:
        return self.spawn or self.connect is not None or self.save is not None or self.serve_web
