"""``swanky-host --workers N``: a live host as N processes, each converting its shard of the
robots (core/shards.py), into one recording.

One host process converts about one core's worth of messages whatever the PC has: 25 demo
robots' traffic needs about two of this machine's (benchmarks/RESULTS.md, fleet), and the
README's two hosts through a router, each half the fleet, converted 2.45 times the small
messages one host did at half its CPU per message. This is that recipe as one command:

* this process is the robots' Zenoh router: it opens the session the flags describe (listening
  for relays, or connected to them or to the lab's router) in router mode, plus a private
  loopback endpoint the workers connect to as clients; Zenoh then forwards each robot's samples
  only to the worker that subscribed to them. With ``--demo`` it also runs the simulated robots'
  relays (their bags written first), which reach it as clients;
* every worker is a ``swanky-host`` of its own (its GIL, queues, sink, ``/_stats``), started
  with the same options but for its shard, the router's endpoint, one viewer (``--spawn``: this
  process starts it) and one recording id, so the viewer shows one recording and the workers
  share its layout (outputs/shared_layout.py). A worker's ``--save`` and ``--record-mcap``
  files carry its name (``FILE-worker0.rrd``; ``rerun FILE-worker*.rrd`` opens them together),
  its viewer lag is ``/_stats/host/worker0/viewer_lag_ms``, and it prints its own summary;
* a stop (Ctrl-C, ``--duration``) reaches every worker, each finishing its files; the exit code
  is the worst of theirs.
"""

from __future__ import annotations

import dataclasses
import logging
import multiprocessing
import os
import signal
import sys
import threading
import uuid
from collections.abc import Callable, Sequence
from contextlib import ExitStack
from pathlib import Path
from typing import TYPE_CHECKING

from host_bridge.core.shards import Shard
from host_bridge.errors import ConfigError
from robot_relay.session import ZenohOptions, close_session

if TYPE_CHECKING:
    from multiprocessing.process import BaseProcess

    from host_bridge.app import HostOptions

log = logging.getLogger("swanky.host")

STOP_WAIT_S = 60.0
"""How long the workers get to finish their files once stopped, before they are terminated."""
POLL_S = 0.1


def shard_path(path: Path | None, shard: Shard) -> Path | None:
    """A worker's own file for the host's ``path``: ``FILE-worker0.rrd``."""
    return None if path is None else path.with_name(f"{path.stem}-{shard.name}{path.suffix}")


def worker_options(
    options: HostOptions, shard: Shard, *, endpoint: str, robots: str, viewer: str | None,
    recording_id: str,
) -> HostOptions:
    """What worker ``shard`` of the host ``options`` runs: its robots, through the router at
    ``endpoint``, into ``viewer`` (the one spawned, or ``--rerun-addr``) and its own files."""
    return dataclasses.replace(
        options,
        workers=1,
        shard=shard,
        demo=False,
        robots=robots,
        zenoh=ZenohOptions(mode="client", connect=(endpoint,), multicast_scouting=False),
        sink=dataclasses.replace(
            options.sink, spawn=False, connect=viewer, save=shard_path(options.sink.save, shard),
            recording_id=recording_id,
        ),
        record_mcap=shard_path(options.record_mcap, shard),
        host_name=shard.name if options.host_name is None else f"{options.host_name}-{shard.name}",
    )


def check_workers(options: HostOptions) -> None:
    """ConfigError naming the flag when ``--workers`` cannot be used as asked."""
    if options.bag is not None:
        msg = "--workers: a bag is converted by one process (--workers is for live robots and --demo)"
        raise ConfigError(msg)
    if options.sink.serve_web:
        msg = ("--workers: --serve-web serves the recording from the host's own process; give the "
               "workers one viewer instead (--spawn, or --rerun-addr URL of a running `rerun`)")
        raise ConfigError(msg)


WorkerMain = Callable[["HostOptions", int], None]
"""A worker process's entry (cli.worker_process): its options and logging level."""


def run_workers(options: HostOptions, stop: threading.Event, worker_main: WorkerMain) -> int:
    """Route the robots to ``options.workers`` processes running ``worker_main`` until they end
    or ``stop``; the worst of their exit codes."""
    from host_bridge.demo.run import DemoRelays, configure_demo, free_loopback_port
    from host_bridge.inputs.live import open_host_session
    from host_bridge.outputs.blueprint import check_blueprint_file
    from host_bridge.outputs.sink import APPLICATION_ID, spawn_viewer

    check_workers(options)
    demo = configure_demo(options.robots) if options.demo else None  # before a viewer opens
    if options.blueprint is not None:
        check_blueprint_file(options.blueprint, APPLICATION_ID)
    recording_id = options.sink.recording_id or str(uuid.uuid4())
    zenoh = options.zenoh if demo is None else demo.host_zenoh(options.zenoh)
    endpoint = demo.endpoint if demo is not None else f"tcp/127.0.0.1:{free_loopback_port()}"
    if endpoint not in zenoh.listen:
        zenoh = dataclasses.replace(zenoh, listen=(*zenoh.listen, endpoint))
    viewer = options.sink.connect
    if options.sink.spawn:
        viewer = spawn_viewer().url
    robots = options.robots if demo is None else demo.robot_filter
    shards = [Shard(index, options.workers) for index in range(options.workers)]
    with ExitStack() as closing:
        session = open_host_session(dataclasses.replace(zenoh, mode="router"))
        closing.callback(close_session, session)
        relays = None
        bags = None
        if demo is not None:
            relays = DemoRelays(demo, stop, options.duration, mode="client")
            closing.callback(relays.close)
            bags = relays.write()
            if bags is None:
                return 0
        context = multiprocessing.get_context("spawn")  # never fork a process running Zenoh
        processes = [
            context.Process(
                target=worker_main, name=f"swanky-host {shard.name}",
                args=(worker_options(options, shard, endpoint=endpoint, robots=robots,
                                     viewer=viewer, recording_id=recording_id),
                      logging.getLogger().level),
            )
            for shard in shards
        ]
        for process in processes:
            process.start()
        closing.callback(_stop_all, processes)
        log.info("%d workers (pids %s) converting the robots, spread by name; recording id %s",
                 len(processes), ", ".join(str(process.pid) for process in processes), recording_id)
        if relays is not None and bags is not None:
            relays.start(bags)
        failed: set[int] = set()
        while not stop.is_set() and any(process.is_alive() for process in processes):
            stop.wait(POLL_S)
            _say_failed(shards, processes, failed)
    _say_failed(shards, processes, failed)
    return max((code if code is not None and code >= 0 else 1) for code in
               (process.exitcode for process in processes))


def _say_failed(shards: Sequence[Shard], processes: Sequence[BaseProcess], said: set[int]) -> None:
    """Name each worker that ended with an error, once, as it ends: its robots are no longer
    converted, the other workers' are."""
    for shard, process in zip(shards, processes, strict=True):
        code = process.exitcode
        if code and shard.index not in said:
            said.add(shard.index)
            how = f"was killed by signal {-code}" if code < 0 else f"exited with code {code}"
            print(f"swanky-host: {shard.name} (pid {process.pid}) {how}: its robots are no longer "
                  f"converted (those whose name's crc32 % {shard.count} is {shard.index}); the other "
                  "workers go on", file=sys.stderr, flush=True)


def _stop_all(processes: Sequence[BaseProcess]) -> None:
    """Stop every running worker as a first Ctrl-C stops a host (SIGTERM: the workers leave
    Ctrl-C to this process, cli.run_worker), then wait for them to finish their files;
    terminated past :data:`STOP_WAIT_S`."""
    for process in processes:
        if process.is_alive() and process.pid is not None:
            os.kill(process.pid, signal.SIGTERM)
    for process in processes:
        process.join(STOP_WAIT_S)
        if process.is_alive():
            log.error("%s did not stop within %.0f s; terminating it", process.name, STOP_WAIT_S)
            process.terminate()
            process.join(5.0)
