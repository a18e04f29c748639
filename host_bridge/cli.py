"""``swanky-host``: runs on the PC; decodes, converts and logs robots (live or bags) to Rerun."""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from host_bridge.dispatch import Dispatcher
from host_bridge.errors import HostError, PartialConvertError
from host_bridge.resources import ResourceResolver, parse_package_path
from host_bridge.sink import RerunSink, SinkOptions
from robot_relay.errors import RelayError
from robot_relay.session import add_zenoh_arguments
from robot_relay.wire import check_robot_name

log = logging.getLogger("swanky.host")


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="swanky-host",
        description="Show ROS robots in Rerun: live from swanky-relay over Zenoh, or from bags.",
    )
    source = parser.add_argument_group("source (default: live robots over Zenoh)")
    source.add_argument("--bag", type=Path, help="convert this bag (rosbag2 dir/.mcap/.db3, .bag)")
    source.add_argument(
        "--robot", default="robot", help="robot name for --bag (entity root, frame prefix)"
    )
    source.add_argument(
        "--demo", action="store_true",
        help="simulated robot through the real relay -> Zenoh -> host path, no hardware",
    )
    source.add_argument(
        "--robots", default="*", metavar="KEYEXPR",
        help="live: only robots matching this key-expression chunk (default: all)",
    )
    out = parser.add_argument_group("Rerun (default: spawn a viewer)")
    out.add_argument(
        "--rerun-addr", "--connect-rerun", dest="rerun_addr", metavar="URL",
        help="send to a running viewer, e.g. rerun+http://127.0.0.1:9876/proxy",
    )
    out.add_argument("--spawn", action="store_true", help="spawn a Rerun viewer")
    out.add_argument("--save", type=Path, metavar="FILE.rrd", help="write a .rrd file")
    out.add_argument(
        "--serve-web", action="store_true", help="serve the web viewer and print its URL"
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
    parser.add_argument(
        "--strict", action="store_true", help="stop on the first bad message instead of warning"
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    add_zenoh_arguments(parser)
    return parser.parse_args(argv)


def sink_options(args: argparse.Namespace) -> SinkOptions:
    options = SinkOptions(
        spawn=args.spawn,
        connect=args.rerun_addr,
        save=args.save,
        serve_web=args.serve_web,
    )
    if not options.any:
        options = SinkOptions(spawn=True)
    return options


def resolver(args: argparse.Namespace) -> ResourceResolver:
    env = ResourceResolver.from_env()
    packages = dict(parse_package_path(option) for option in args.package_path)
    return ResourceResolver(packages, env.search_paths)


def log_urdf_file(args: argparse.Namespace, dispatcher: Dispatcher) -> None:
    """The --urdf model of robot --robot, logged once (static) before any data."""
    from host_bridge.converters.urdf import model_items_from_file
    from host_bridge.registry import ConvertContext

    ctx = ConvertContext(
        robot=args.robot, topic="/robot_description", entity_path=f"/{args.robot}/robot_model",
        times={}, robot_state=dispatcher.robot_state(args.robot),
    )
    try:
        dispatcher.sink.log(model_items_from_file(args.urdf, ctx), {})
    except PartialConvertError as err:
        dispatcher.sink.log(err.items, {})
        dispatcher.warn(args.robot, str(args.urdf), err)


def convert_bag(args: argparse.Namespace, dispatcher: Dispatcher, stop: threading.Event) -> None:
    from host_bridge.inputs.bag import bag_runs

    for run in bag_runs(args.bag, args.robot):
        dispatcher.dispatch(run)
        if stop.is_set():
            break


def run_live(
    args: argparse.Namespace, dispatcher: Dispatcher, stop: threading.Event
) -> None:
    """Dispatch live samples until stopped, ``--duration`` or ``--until-idle``."""
    from host_bridge.inputs.zenoh import InputProblem, ZenohInput
    from robot_relay.session import open_session

    session = open_session(args)
    source = ZenohInput(session, robots=args.robots)
    started = last_data = time.monotonic()
    try:
        while not stop.is_set():
            items = source.drain()
            now = time.monotonic()
            if items:
                last_data = now
                batch = []
                for item in items:
                    if isinstance(item, InputProblem):
                        dispatcher.warn(item.robot, item.topic, item.error)
                    else:
                        batch.append(item)
                dispatcher.dispatch(batch)
            if args.duration is not None and now - started >= args.duration:
                break
            if args.until_idle is not None and now - last_data >= args.until_idle:
                log.info("no data for %.1f s, stopping", args.until_idle)
                break
    finally:
        source.close()
        session.close()


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(name)s: %(levelname)s: %(message)s",
    )
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    sink: RerunSink | None = None
    try:
        check_robot_name(args.robot)
        if args.bag is not None and not args.bag.exists():
            print(f"swanky-host: error: bag {args.bag} does not exist", file=sys.stderr)
            return 2
        sink = RerunSink(sink_options(args))
        if sink.web_url:
            print(f"Rerun web viewer: {sink.web_url}", flush=True)
        dispatcher = Dispatcher(
            sink, strict=args.strict, robot_state={"resolver": resolver(args)}
        )
        if args.urdf is not None:
            log_urdf_file(args, dispatcher)
        if args.bag is not None:
            convert_bag(args, dispatcher, stop)
            if args.serve_web and not stop.is_set():
                # The web viewer lives in this process: keep serving the converted bag.
                print("bag converted; serving the web viewer until Ctrl-C", file=sys.stderr)
                stop.wait(args.duration)
        elif args.demo:
            from host_bridge.demo import run_demo

            run_demo(args, lambda: run_live(args, dispatcher, stop), stop)
        else:
            run_live(args, dispatcher, stop)
        dispatcher.close()
        print(dispatcher.summary(), file=sys.stderr)
    except (HostError, RelayError) as err:
        print(f"swanky-host: error: {err}", file=sys.stderr)
        return 2
    finally:
        if sink is not None:
            sink.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
