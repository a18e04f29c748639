"""``swanky-host``: runs on the PC; decodes, converts and logs robots (live or bags) to Rerun.

This module only turns flags into a :class:`~host_bridge.app.HostOptions` record and the
process's signals into a stop event; ``host_bridge/app.py`` does the rest."""

from __future__ import annotations

import argparse
import atexit
import gc
import importlib
import logging
import os
import signal
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from host_bridge.core.destinations import LOOPBACK, SAVE_SPLIT_S, SinkOptions
from host_bridge.errors import HostError
from robot_relay.session import add_zenoh_arguments, zenoh_options
from robot_relay.signals import StopSignals

if TYPE_CHECKING:
    # Imported when the host runs, not for --help: the app loads Rerun and the converters.
    from host_bridge import app
    from host_bridge.inputs.bag_opener import BagOpener

log = logging.getLogger("swanky.host")


def default_domain() -> int:
    value = os.environ.get("ROS_DOMAIN_ID", "").strip()
    return int(value) if value.isdigit() else 0


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="swanky-host",
        description="Show ROS robots in Rerun: live from swanky-relay over Zenoh, or from bags.",
    )
    source = parser.add_argument_group("source (default: live robots over Zenoh)")
    source.add_argument("--bag", type=Path, help="convert this bag (rosbag2 dir/.mcap/.db3, .bag)")
    source.add_argument(
        "--robot", default="robot",
        help="robot name (entity root, frame prefix) for --bag, and for rmw_zenoh nodes that "
        "have no ROS namespace",
    )
    source.add_argument(
        "--demo", action="store_true",
        help="simulated robot through the real relay -> Zenoh -> host path, no hardware; "
        "--demo --robots N: a fleet of N (sim, sim2, ...)",
    )
    source.add_argument(
        "--robots", default="*", metavar="KEYEXPR",
        help="live: only robots matching this Zenoh key-expression chunk: a name, '*' (default: "
        "all) or '$*' inside a name ('east-$*'); applies to relays and rmw_zenoh robots. With "
        "--demo: the number of simulated robots",
    )
    source.add_argument(
        "--domain", type=int, default=default_domain(), metavar="N",
        help="ROS domain of rmw_zenoh robots read directly (default: ROS_DOMAIN_ID, else 0)",
    )
    source.add_argument(
        "--no-rmw-zenoh", dest="rmw_zenoh", action="store_false",
        help="live: only swanky relays; do not read rmw_zenoh robots directly",
    )
    source.add_argument(
        "--list", action="store_true",
        help="print the robots and topics seen live for --duration seconds (default 3), with "
        "rates and bandwidth, then exit; nothing goes to Rerun",
    )
    out = parser.add_argument_group("Rerun (default: spawn a viewer)")
    out.add_argument(
        "--rerun-addr", "--connect-rerun", dest="rerun_addr", metavar="URL",
        help="send to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy",
    )
    out.add_argument("--spawn", action="store_true", help="spawn a Rerun viewer")
    out.add_argument("--save", type=Path, metavar="FILE.rrd", help="write a .rrd file")
    out.add_argument(
        "--save-split", type=float, default=SAVE_SPLIT_S, metavar="SECONDS",
        help=f"live: go on in a new --save file every SECONDS (default {SAVE_SPLIT_S:g}): "
        "FILE.rrd becomes FILE_0.rrd, then FILE_1.rrd, ...; `rerun FILE_*.rrd` opens them as one",
    )
    out.add_argument(
        "--serve-web", action="store_true", help="serve the web viewer and print its URL"
    )
    out.add_argument(
        "--record-mcap", type=Path, metavar="FILE.mcap",
        help="also record every raw message received to a ROS 2 MCAP file (ros2 bag, Foxglove)",
    )
    out.add_argument(
        "--stats", action=argparse.BooleanOptionalAction, default=None,
        help="log rate, bandwidth, drops, latency and conversion time under /_stats "
        "(default: on live, off for --bag, where it runs on bag time)",
    )
    out.add_argument("--web-port", type=int, metavar="PORT", help="--serve-web: HTTP port (9090)")
    out.add_argument(
        "--recording-id", metavar="ID",
        help="Rerun recording id: hosts of one fleet given the same id fill one recording in a "
        "shared viewer (default: a new id per run)",
    )
    out.add_argument(
        "--host-name", type=host_name, metavar="NAME",
        help="one of several hosts sharing a viewer (--recording-id): this host's viewer lag goes "
        "to /_stats/host/NAME/viewer_lag_ms, apart from the others' (default: /_stats/host/...)",
    )
    out.add_argument(
        "--grpc-port", type=int, metavar="PORT", help="--serve-web: gRPC port the viewer reads (9876)"
    )
    out.add_argument(
        "--web-bind", default=LOOPBACK, metavar="ADDR",
        help=f"--serve-web: address the recording is served on (default {LOOPBACK}: this PC only; "
        "0.0.0.0 or :: opens it to the network). Rerun serves the viewer page itself (code, no "
        "data) on every interface",
    )
    layout = out.add_mutually_exclusive_group()
    layout.add_argument(
        "--no-blueprint", action="store_true",
        help="do not send Swanky's layout (Rerun then arranges the views itself)",
    )
    layout.add_argument(
        "--blueprint", type=Path, metavar="FILE.rbl",
        help="send this saved Rerun blueprint instead of Swanky's layout",
    )
    source.add_argument(
        "--workers", type=worker_count, default=1, metavar="N",
        help="live: convert the robots in N processes, each robot in one (spread by name), into "
        "one recording: one process converts about one core's worth of messages (default 1)",
    )
    slam = parser.add_argument_group("mapping (host-side 2D SLAM from /scan and odometry)")
    slam.add_argument(
        "--slam", action="store_true",
        help="build each robot's map on this PC from its LaserScan and odometry (on by default "
        "with --demo; per-robot settings: the slam: block of --config)",
    )
    slam.add_argument(
        "--no-slam", action="store_true",
        help="with --demo: show the simulated robot without the host's map",
    )
    slam.add_argument(
        "--save-map", type=Path, metavar="DIR",
        help="at the end, write DIR/<robot>/map.yaml + map.pgm (nav2 map_saver format) and "
        "DIR/<robot>/trajectory.tum (implies --slam)",
    )
    stop = parser.add_argument_group("stopping (default: Ctrl-C; bags stop at their end)")
    stop.add_argument(
        "--duration", type=float, metavar="SECONDS", help="stop after this many seconds"
    )
    stop.add_argument(
        "--until-idle", type=float, metavar="SECONDS",
        help="stop once no data arrived for this long",
    )
    model = parser.add_argument_group("robot model")
    model.add_argument(
        "--urdf", type=Path, metavar="PATH",
        help="robot model for --robot from a file (xacro expanded), instead of /robot_description",
    )
    model.add_argument(
        "--package-path", action="append", default=[], metavar="NAME=DIR",
        help="where package://NAME/... meshes are (repeatable); then ROS_PACKAGE_PATH, "
        "AMENT_PREFIX_PATH",
    )
    config = parser.add_argument_group("configuration")
    config.add_argument(
        "--config", type=Path, metavar="FILE.yaml",
        help="per-topic entity path, enabled, converter, options, restamp (schemas/host.schema.json)",
    )
    config.add_argument(
        "--print-config", action="store_true",
        help="print the effective configuration (--config over the built-in defaults) as YAML, exit",
    )
    parser.add_argument(
        "--strict", action="store_true", help="stop on the first bad message instead of warning"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_zenoh_arguments(parser)
    return parser.parse_args(argv)


MAX_WORKERS = 64


def worker_count(text: str) -> int:
    """``--workers``: 1 to :data:`MAX_WORKERS` processes."""
    try:
        count = int(text)
    except ValueError:
        count = 0
    if not 1 <= count <= MAX_WORKERS:
        msg = f"{text!r} is not a number of worker processes: 1 to {MAX_WORKERS}"
        raise argparse.ArgumentTypeError(msg)
    return count


def host_name(name: str) -> str:
    """``--host-name``: one part of a Rerun entity path."""
    if not name or "/" in name or any(char.isspace() for char in name):
        msg = f"{name!r} is not a host name: one word of an entity path, without '/' or spaces"
        raise argparse.ArgumentTypeError(msg)
    return name


def sink_options(args: argparse.Namespace) -> SinkOptions:
    options = SinkOptions(
        spawn=args.spawn,
        connect=args.rerun_addr,
        save=args.save,
        serve_web=args.serve_web,
        web_port=args.web_port,
        grpc_port=args.grpc_port,
        web_bind=args.web_bind,
        recording_id=args.recording_id,
        save_split_s=None if args.bag is not None else args.save_split,  # a bag's file ends
    )
    if not options.any:
        options = SinkOptions(spawn=True)
    return options


def host_options(args: argparse.Namespace) -> app.HostOptions:
    from host_bridge import app

    return app.HostOptions(
        sink=sink_options(args),
        zenoh=zenoh_options(args),
        bag=args.bag,
        robot=args.robot,
        demo=args.demo,
        robots=args.robots,
        domain=args.domain,
        rmw_zenoh=args.rmw_zenoh,
        list_topics=args.list,
        record_mcap=args.record_mcap,
        stats=args.stats,
        host_name=args.host_name,
        blueprint=args.blueprint,
        send_layout=not args.no_blueprint,
        duration=args.duration,
        until_idle=args.until_idle,
        urdf=args.urdf,
        package_path=tuple(args.package_path),
        config=args.config,
        print_config=args.print_config,
        strict=args.strict,
        slam=not args.no_slam and (args.slam or args.save_map is not None or args.demo),
        save_map=args.save_map,
        workers=args.workers,
    )


def import_app_uncollected() -> None:
    """Import :mod:`host_bridge.app` (Rerun, numpy, pyarrow, the converters) with the garbage
    collector off, then freeze what it made.

    The import makes about 100k tracked objects that live as long as the process; collecting
    while it ran cost ~150 collections, 60-85 ms of a 0.5-0.8 s import (gc.callbacks), and
    every later full collection would walk them again. Only the first import: a process that
    calls :func:`main` again (the tests) keeps collecting as before."""
    if "host_bridge.app" in sys.modules:
        return
    collecting = gc.isenabled()
    gc.disable()
    try:
        importlib.import_module("host_bridge.app")
    finally:
        if collecting:
            gc.enable()
    gc.freeze()


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(name)s: %(levelname)s: %(message)s",
    )
    signals = StopSignals("swanky-host", log)
    signals.install()
    bag_opener = None
    if args.bag is not None and not args.print_config:
        from host_bridge.inputs.bag_opener import BagOpener
        from robot_relay.heap import keep_freed_buffers

        # A bag's large chunks and messages reuse freed heap, as the live relay's messages do: a
        # --compression-mode file bag of images decompresses each chunk into a new 1 MB buffer
        # (1.09-1.14 s wall instead of 1.19-1.51, 4 runs each, alternated; the other layouts as
        # before, peak RSS within 2 %).
        keep_freed_buffers()
        bag_opener = BagOpener(args.bag, args.robot)  # opens while the app is imported
    return run_app(lambda: host_options(args), signals, bag_opener)


def worker_process(options: app.HostOptions, level: int) -> NoReturn:
    """One of ``--workers N`` processes (host_bridge/workers.py starts it): the host of its
    shard's robots. Ctrl-C reaches every process of the terminal; the workers leave it to the
    process that started them, which stops them with SIGTERM once and waits for their files."""
    assert options.shard is not None
    logging.basicConfig(
        level=level, format=f"%(name)s ({options.shard.name}): %(levelname)s: %(message)s"
    )
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signals = StopSignals("swanky-host", log)
    signals.install(signal.SIGTERM)
    sys.exit(run_app(lambda: options, signals))


def run_app(
    options: Callable[[], app.HostOptions], signals: StopSignals, bag_opener: BagOpener | None = None
) -> int:
    """The host with ``options()`` (made once the app is imported) until it ends or ``signals``
    stop it; its exit code."""
    import_app_uncollected()
    from host_bridge import app

    outputs = app.Outputs()
    try:
        chosen = options()
        if chosen.workers > 1 and not (chosen.list_topics or chosen.print_config):
            from host_bridge.workers import run_workers

            code = run_workers(chosen, signals.stop, worker_process)
        else:
            code = app.run(chosen, signals.stop, lambda: signals.received, outputs, bag_opener)
    except HostError as err:
        print(f"swanky-host: error: {err}", file=sys.stderr)
        code = 2
    finally:
        complete = outputs.close()
        if bag_opener is not None:
            bag_opener.close()
    code = code if complete else max(code, 1)
    if outputs.sink is not None and outputs.sink.abandoned:
        # Rerun's exit handler would wait for the viewer that stopped answering, too.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


def console_main() -> NoReturn:
    """The ``swanky-host`` command: :func:`main`, then out of the process without finalizing
    Python, once the threads that must end have (as Python would wait for them) and the exit
    handlers have run (Rerun's flushes what it still holds). Zenoh's own threads (the demo's
    relays, the robots' sessions) may still call into Python while it finalizes; CPython then
    ends such a thread by unwinding it, which its Rust frames turn into an abort ("FATAL:
    exception not rethrown", exit 134 after ``swanky-host --demo --save`` had printed its
    summary), as swanky-relay's own exit explains. Skipping finalization also skips its last
    full garbage collection (0.25-0.3 s after converting a large bag). Not in :func:`main`,
    which tests call in their own process."""
    # Before numpy loads OpenBLAS: its second thread spins, 0.1 s of CPU while a bag converts
    # (4 % of a large bag's perf samples in blas_thread_server), and the host's matrix products
    # have an inner size of 2 to 4 (SLAM's scan points by a pose), which threads only slow
    # (converters/segments.py's _rotated). A user's own setting is kept.
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    code = main()
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    atexit._run_exitfuncs()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    console_main()
