"""``swanky-host``: runs on the PC; decodes, converts and logs robots (live or bags) to Rerun."""

from __future__ import annotations

import argparse
import logging
import os
import signal
import sys
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from host_bridge.blueprint import BlueprintFollower, check_blueprint_file
from host_bridge.config import HostConfig
from host_bridge.dispatch import Dispatcher
from host_bridge.errors import HostError, PartialConvertError, SinkError
from host_bridge.inputs.queues import InputProblem, QueueItem, RobotEvent, presence_items
from host_bridge.recorder import McapRecorder, may_hold_several_robots
from host_bridge.registry import default_registry
from host_bridge.resources import ResourceResolver, RobotFetch, parse_package_path
from host_bridge.robot_files import RobotFiles
from host_bridge.sink import APPLICATION_ID, LOOPBACK, RerunSink, SinkOptions
from robot_relay.errors import RelayError
from robot_relay.session import add_zenoh_arguments
from robot_relay.wire import check_robot_name

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
    )
    if not options.any:
        options = SinkOptions(spawn=True)
    return options


def resolver(args: argparse.Namespace, robot_fetch: RobotFetch | None = None) -> ResourceResolver:
    env = ResourceResolver.from_env()
    packages = dict(parse_package_path(option) for option in args.package_path)
    return ResourceResolver(packages, env.search_paths, robot_fetch=robot_fetch)


def log_urdf_file(args: argparse.Namespace, dispatcher: Dispatcher) -> None:
    """The --urdf model of robot --robot, logged once (static) before any data; the robot's
    /robot_description is then not drawn."""
    from host_bridge.contract import ConvertContext
    from host_bridge.converters.urdf import model_items_from_file

    ctx = ConvertContext(
        robot=args.robot, topic="/robot_description", entity_path=f"/{args.robot}/robot_model",
        times={}, robot_state=dispatcher.robot_state(args.robot),
    )
    try:
        dispatcher.log(args.robot, model_items_from_file(args.urdf, ctx), {})
    except PartialConvertError as err:
        dispatcher.log(args.robot, err.items, {})
        dispatcher.warn(args.robot, str(args.urdf), err)


def start_layout(args: argparse.Namespace, sink: RerunSink) -> BlueprintFollower | None:
    """The user's --blueprint file, sent once; else Swanky's layout following the topics,
    unless --no-blueprint."""
    if args.blueprint is not None:
        sink.send_blueprint_file(args.blueprint)
        return None
    if args.no_blueprint:
        return None
    stats = args.stats if args.stats is not None else args.bag is None
    return BlueprintFollower(sink.send_blueprint, stats=stats)


def convert_bag(args: argparse.Namespace, dispatcher: Dispatcher, stop: threading.Event) -> None:
    from host_bridge.inputs.bag import bag_runs
    from host_bridge.progress import Progress, bag_extent
    from host_bridge.stats import StatsTap

    progress = Progress(bag_extent(args.bag))
    dispatcher.taps.append(progress)
    if args.stats:
        dispatcher.taps.append(StatsTap(dispatcher.sink, dispatcher.counters))
    for run in bag_runs(args.bag, args.robot):
        dispatcher.dispatch(run)
        if stop.is_set():
            break
    progress.finish()


def handle_items(dispatcher: Dispatcher, items: Sequence[QueueItem]) -> None:
    """One robot's run of input items: problems warned about, arrivals logged, data dispatched."""
    batch = []
    for item in items:
        if isinstance(item, InputProblem):
            dispatcher.warn(item.robot, item.topic, item.error)
        elif isinstance(item, RobotEvent):
            log.info("%s", item.text)
            dispatcher.sink.log(presence_items(item, time.time_ns()), {})
        else:
            batch.append(item)
    if batch:
        dispatcher.dispatch(batch)


def run_live(
    args: argparse.Namespace, dispatcher: Dispatcher, stop: threading.Event,
    robot_files: RobotFiles | None = None,
) -> None:
    """Dispatch live samples until stopped, ``--duration`` or ``--until-idle``. Each robot is
    dispatched from its own thread (inputs/queues.py): a slow or broken robot delays only itself."""
    from host_bridge.inputs.queues import RobotQueues
    from host_bridge.inputs.rmw_zenoh import RmwZenohInput
    from host_bridge.inputs.zenoh import ZenohInput
    from host_bridge.stats import StatsTap
    from robot_relay.session import open_session

    session = open_session(args)
    if robot_files is not None:
        robot_files.attach(session)
    queues = RobotQueues()
    sources: list[ZenohInput | RmwZenohInput] = [
        ZenohInput(session, robots=args.robots, queues=queues)
    ]
    if args.rmw_zenoh:
        sources.append(RmwZenohInput(session, args.domain, args.robots, args.robot, queues))
    stats = None if args.stats is False else StatsTap(
        dispatcher.sink, dispatcher.counters, session=session, robots=args.robots
    )
    if stats is not None:
        dispatcher.taps.append(stats)
    queues.serve(lambda items: handle_items(dispatcher, items))
    started = time.monotonic()
    try:
        while not stop.wait(0.05):
            if queues.error is not None:
                raise queues.error
            now = time.monotonic()
            if args.duration is not None and now - started >= args.duration:
                break
            if args.until_idle is not None and now - queues.last_activity >= args.until_idle:
                log.info("no data for %.1f s, stopping", args.until_idle)
                break
    finally:
        for source in sources:
            source.close()
        queues.close()
        if stats is not None:
            stats.close()
        if robot_files is not None:
            robot_files.detach()
        session.close()
    if queues.dropped:
        log.warning("messages dropped because the host fell behind:\n%s", queues.drop_summary())
    if queues.error is not None:
        raise queues.error


class StopSignals:
    """SIGINT and SIGTERM: the first stops the host cleanly (a saved .rrd is completed), a second
    exits at once, as swanky-relay does. Everything the main thread waits on is bounded in short
    steps (sink.py, run_live), so the handler always gets to run within about a second."""

    def __init__(self, stop: threading.Event) -> None:
        self.stop = stop
        self.received = False

    def install(self) -> None:
        signal.signal(signal.SIGINT, self._on_signal)
        signal.signal(signal.SIGTERM, self._on_signal)

    def _on_signal(self, signum: int, frame: object) -> None:
        name = signal.Signals(signum).name
        if self.received:  # the user does not want to wait for the files and viewers
            print(f"swanky-host: {name} again, exiting at once", file=sys.stderr, flush=True)
            os._exit(128 + signum)
        self.received = True
        log.info("%s: stopping (again to force)", name)
        self.stop.set()


@dataclass
class Outputs:
    """What the host writes to, closed in reverse order of opening whatever happened."""

    sink: RerunSink | None = None
    layout: BlueprintFollower | None = None
    recorder: McapRecorder | None = None

    def close(self) -> bool:
        """Close everything; False (and said why on stderr) when a viewer missed data."""
        if self.recorder is not None:
            self.recorder.close()
        if self.layout is not None:
            self.layout.close()
        if self.sink is None:
            return True
        try:
            self.sink.close()
        except SinkError as err:
            print(f"swanky-host: error: {err}", file=sys.stderr)
            return False
        return True


def run_host(args: argparse.Namespace, signals: StopSignals, outputs: Outputs) -> int:
    stop = signals.stop
    check_robot_name(args.robot)
    if args.list:
        from host_bridge.listing import run_list

        return run_list(args, stop)
    registry = default_registry()
    config = (
        HostConfig.load(args.config, registry.types()) if args.config is not None
        else HostConfig.builtin(registry.types())
    )
    if args.print_config:
        print(config.dump(), end="")
        return 0
    if args.bag is not None and not args.bag.exists():
        print(f"swanky-host: error: bag {args.bag} does not exist", file=sys.stderr)
        return 2
    if args.demo:
        from host_bridge.demo.run import configure_demo

        configure_demo(args)  # checks --robots N before a viewer opens
    if args.blueprint is not None:
        check_blueprint_file(args.blueprint, APPLICATION_ID)
    # Live robots serve the meshes this PC lacks (robot_relay/files.py).
    robot_files = None if args.bag is not None else RobotFiles()
    meshes = resolver(args, None if robot_files is None else robot_files.fetch)  # checks dirs
    # After a stop signal a slow viewer is not waited for.
    sink = outputs.sink = RerunSink(sink_options(args), give_up=lambda: signals.received)
    if sink.web_url:
        print(f"Rerun web viewer: {sink.web_url}", flush=True)
        print(f"swanky-host: {sink.web_note}", file=sys.stderr)
    layout = outputs.layout = start_layout(args, sink)
    dispatcher = Dispatcher(
        sink, registry=registry, config=config, strict=args.strict,
        resolver=meshes,
        on_new_topic=None if layout is None else layout.topic_seen,
    )
    if args.record_mcap is not None:
        outputs.recorder = McapRecorder(args.record_mcap, prefix_robot=may_hold_several_robots(
            bag=args.bag is not None, demo=args.demo and len(args.demo_robots) == 1,
            robots=args.robots))
        dispatcher.taps.append(outputs.recorder)
    if args.urdf is not None:
        log_urdf_file(args, dispatcher)
    if args.bag is not None:
        convert_bag(args, dispatcher, stop)
        if args.serve_web and not stop.is_set():
            # The web viewer lives in this process: keep serving the converted bag.
            print("bag converted; serving the web viewer until Ctrl-C", file=sys.stderr)
            stop.wait(args.duration)
    elif args.demo:
        from host_bridge.demo.run import run_demo

        run_demo(args, lambda: run_live(args, dispatcher, stop, robot_files), stop)
    else:
        run_live(args, dispatcher, stop, robot_files)
    dispatcher.close()
    print(dispatcher.summary(), file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(name)s: %(levelname)s: %(message)s",
    )
    signals = StopSignals(threading.Event())
    signals.install()
    outputs = Outputs()
    try:
        code = run_host(args, signals, outputs)
    except (HostError, RelayError) as err:
        print(f"swanky-host: error: {err}", file=sys.stderr)
        code = 2
    finally:
        complete = outputs.close()
    code = code if complete else max(code, 1)
    if outputs.sink is not None and outputs.sink.abandoned:
        # Rerun's exit handler would wait for the viewer that stopped answering, too.
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)
    return code


if __name__ == "__main__":
    sys.exit(main())
