"""Where a recording goes (``--spawn``, ``--rerun-addr``, ``--save``, ``--serve-web``), as a
record :mod:`host_bridge.cli` fills without importing Rerun: ``swanky-host --help`` must not pay
for loading the SDK. :mod:`host_bridge.sink` opens what it names."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

LOOPBACK = "127.0.0.1"


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

    @property
    def any(self) -> bool:
        return self.spawn or self.connect is not None or self.save is not None or self.serve_web
