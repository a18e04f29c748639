"""``swanky-host``'s wiring: options -> one input -> the dispatcher -> the outputs.

cli.py turns the flags into a :class:`HostOptions` record and the process's signals into a stop
event; everything here reads records only. The input is a :class:`~host_bridge.inputs.base.Input`
(a bag, live robots over Zenoh, the demo); the outputs are the Rerun sink with its layout, and
the dispatcher's taps (``--record-mcap``, ``/_stats``, the bag's progress line).
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from host_bridge.core.destinations import SinkOptions
from host_bridge.core.resources import ResourceResolver, RobotFetch, parse_package_path
from host_bridge.core.shards import Shard
from host_bridge.errors import PartialConvertError, SinkError, relay_errors
from host_bridge.inputs.base import Input
from host_bridge.inputs.robot_files import RobotFiles
from host_bridge.outputs.blueprint import BlueprintFollower, check_blueprint_file
from host_bridge.outputs.recorder import McapRecorder, RawOutput, may_hold_several_robots
from host_bridge.outputs.sink import APPLICATION_ID, RerunSink
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import default_registry
from robot_relay.session import ZenohOptions, close_session
from robot_relay.wire import check_robot_name

if TYPE_CHECKING:
    from host_bridge.demo.run import DemoPlan
    from host_bridge.inputs.bag import BagExtent
    from host_bridge.inputs.bag_opener import BagOpener
    from host_bridge.pipeline.offload import HeavyProcess
    from host_bridge.slam.feeder import SlamTap

log = logging.getLogger("swanky.host")

POLL_S = 0.05
"""How often the main thread looks at the input, the clock and the stop event."""


@dataclass(frozen=True, slots=True)
class HostOptions:
    """Everything ``swanky-host`` was asked to do (cli.py reads it from the flags)."""

    sink: SinkOptions = field(default_factory=lambda: SinkOptions(spawn=True))
    zenoh: ZenohOptions = field(default_factory=ZenohOptions)
    bag: Path | None = None
    robot: str = "robot"
    demo: bool = False
    robots: str = "*"
    """Live: a Zenoh key chunk of robot names; with ``demo``: how many simulated robots."""
    domain: int = 0
    rmw_zenoh: bool = True
    list_topics: bool = False
    record_mcap: Path | None = None
    stats: bool | None = None
    """None: on live, off for a bag."""
    host_name: str | None = None
    """One of several hosts sharing a viewer: its own ``/_stats/host/<name>/viewer_lag_ms``."""
    blueprint: Path | None = None
    send_layout: bool = True
    duration: float | None = None
    until_idle: float | None = None
    urdf: Path | None = None
    package_path: tuple[str, ...] = ()
    config: Path | None = None
    print_config: bool = False
    strict: bool = False
    slam: bool = False
    """Host-side SLAM for every robot (the config's slam: block may also turn it on per robot)."""
    save_map: Path | None = None
    workers: int = 1
    """Live: host processes converting the robots, each its shard of them (workers.py)."""
    shard: Shard | None = None
    """Set in each of those processes: the robots it converts."""


@dataclass
class Outputs:
    """What the host writes to, closed in reverse order of opening whatever happened."""

    sink: RerunSink | None = None
    layout: BlueprintFollower | None = None
    recorder: RawOutput | None = None
    offload: HeavyProcess | None = None
    slam: SlamTap | None = None

    def close(self) -> bool:
        """Close everything; False (and said why on stderr) when a viewer missed data."""
        if self.slam is not None:  # maps what it holds first: its last map goes to the sink
            self.slam.close()
        if self.recorder is not None:
            self.recorder.close()
        if self.layout is not None:
            self.layout.close()
        if self.sink is None:
            return True
        problems = []
        try:
            self.sink.close()
        except SinkError as err:
            problems.append(str(err))
        # The heavy topics' process closes its own sink meanwhile (offload.py).
        if self.offload is not None and (problem := self.offload.finish()) is not None:
            problems.append(problem)
        for problem in problems:
            print(f"swanky-host: error: {problem}", file=sys.stderr)
        return not problems


def resolver(package_path: tuple[str, ...], robot_fetch: RobotFetch | None = None) -> ResourceResolver:
    env = ResourceResolver.from_env()
    packages = dict(parse_package_path(option) for option in package_path)
    return ResourceResolver(packages, env.search_paths, robot_fetch=robot_fetch)


def log_urdf_file(robot: str, urdf: Path, dispatcher: Dispatcher) -> None:
    """The --urdf model of robot --robot, logged once (static) before any data; the robot's
    /robot_description is then not drawn."""
    from host_bridge.converters.urdf.description import model_items_from_file
    from host_bridge.core.contract import ConvertContext

    ctx = ConvertContext(
        robot=robot, topic="/robot_description", entity_path=f"/{robot}/robot_model",
        times={}, robot_state=dispatcher.robot_state(robot),
    )
    try:
        dispatcher.log(robot, model_items_from_file(urdf, ctx), {})
    except PartialConvertError as err:
        dispatcher.log(robot, err.items, {})
        dispatcher.warn(robot, str(urdf), err)


def start_layout(options: HostOptions, sink: RerunSink) -> BlueprintFollower | None:
    """The user's --blueprint file, sent once; else Swanky's layout following the topics,
    unless --no-blueprint."""
    if options.blueprint is not None:
        sink.send_blueprint_file(options.blueprint)
        return None
    if not options.send_layout:
        return None
    stats = options.stats if options.stats is not None else options.bag is None
    return BlueprintFollower(sink.send_blueprint, stats=stats)


def open_input(
    options: HostOptions, dispatcher: Dispatcher, *, demo: DemoPlan | None,
    robot_files: RobotFiles | None, stop: threading.Event, closing: ExitStack,
    bag_opener: BagOpener | None = None, layout: BlueprintFollower | None = None,
) -> Input:
    """The input the options name, with the taps that go with it; ``closing`` closes what was
    opened (the input first, the Zenoh session last). A live host given ``--recording-id``
    shares ``layout``'s topics with the other hosts of that recording (shared_layout.py)."""
    from host_bridge.outputs.stats import StatsTap

    if options.bag is not None:
        from host_bridge.inputs.bag import BagInput

        if options.stats:
            dispatcher.add_tap(StatsTap(dispatcher.sink, dispatcher.counters))
        bag: Input = BagInput(options.bag, options.robot, bag_opener)
        closing.callback(bag.close)
        return bag
    from host_bridge.inputs.live import LiveInput, open_host_session

    zenoh, robots = options.zenoh, options.robots
    if demo is not None:
        zenoh, robots = demo.host_zenoh(zenoh), demo.robot_filter
    session = open_host_session(zenoh)
    closing.callback(close_session, session)
    if robot_files is not None:
        robot_files.attach(session)
        closing.callback(robot_files.detach)
    if layout is not None and options.sink.recording_id is not None:
        from host_bridge.outputs.shared_layout import SharedLayout

        closing.callback(SharedLayout(session, options.sink.recording_id, layout).close)
    live = LiveInput(
        session, robots=robots, domain=options.domain, root_robot=options.robot,
        rmw_zenoh=options.rmw_zenoh, shard=options.shard,
    )
    if options.stats is not False:
        from host_bridge.pipeline.thinning import ViewerThinning

        thinning = dispatcher.offload
        stats: RawOutput = StatsTap(
            dispatcher.sink, dispatcher.counters, session=session, robots=robots,
            owns=None if options.shard is None else options.shard.owns,
            host_dropped=live.queues.dropped_when_taken, clocks=live.clocks,
            hold_s=(thinning.stats_hold_s if isinstance(thinning, ViewerThinning) else lambda: 0.0),
        )
        dispatcher.add_tap(stats)
        closing.callback(stats.close)  # after the input's: its queues' last drops are counted
    source: Input = live
    if demo is not None:
        from host_bridge.demo.run import DemoInput

        source = DemoInput(demo, live, stop, options.duration)
    closing.callback(source.close)
    return source


def bag_finished(source: Input) -> threading.Event | None:
    """What a bag input sets once it has delivered its last run."""
    from host_bridge.inputs.bag import BagInput

    return source.finished if isinstance(source, BagInput) else None


def bag_extent(source: Input) -> BagExtent | None:
    """What a bag input's bag holds (None for other inputs): opens the bag it then reads."""
    from host_bridge.inputs.bag import BagInput

    return source.extent() if isinstance(source, BagInput) else None


def wait_for_end(
    source: Input, stop: threading.Event, duration: float | None, until_idle: float | None,
    ended: threading.Event | None = None,
) -> None:
    """Until the input ends (a bag) or the host stops: a signal, ``duration`` seconds, or no
    data for ``until_idle`` seconds. ``ended``: set by an input that ends, whose end is then
    seen at once rather than at the next poll (up to POLL_S later, on every bag)."""
    started = time.monotonic()
    woken_by = stop if ended is None else ended
    while not stop.is_set():
        woken_by.wait(POLL_S)
        if source.ended():
            return
        now = time.monotonic()
        if duration is not None and now - started >= duration:
            return
        if until_idle is not None and now - source.last_activity >= until_idle:
            log.info("no data for %.1f s, stopping", until_idle)
            return


def run(
    options: HostOptions, stop: threading.Event, give_up: Callable[[], bool], outputs: Outputs,
    bag_opener: BagOpener | None = None,
) -> int:
    """Run the host until its input ends or ``stop`` is set; ``give_up()``: a stop signal came,
    so a slow viewer is not waited for. The exit code; HostErrors are the caller's to print.
    ``bag_opener``: the bag of ``options`` opening since before the app was imported (cli.py),
    which the bag input takes (the caller closes an opener whose bag was never taken)."""
    with relay_errors():
        check_robot_name(options.robot)
    if options.list_topics:
        from host_bridge.listing import run_list

        return run_list(options.zenoh, options.robots, options.duration, stop)
    registry = default_registry()
    config = (
        HostConfig.load(options.config, registry) if options.config is not None
        else HostConfig.builtin(registry)
    )
    if options.print_config:
        print(config.dump(), end="")
        return 0
    if options.bag is not None and not options.bag.exists():
        print(f"swanky-host: error: bag {options.bag} does not exist", file=sys.stderr)
        return 2
    demo = None
    if options.demo:
        from host_bridge.demo.run import configure_demo

        demo = configure_demo(options.robots)  # checks --robots N before a viewer opens
    if options.blueprint is not None:
        check_blueprint_file(options.blueprint, APPLICATION_ID)
    # Live robots serve the meshes this PC lacks (robot_relay/files.py).
    robot_files = None if options.bag is not None else RobotFiles()
    meshes = resolver(options.package_path, None if robot_files is None else robot_files.fetch)
    live = options.bag is None
    sink = outputs.sink = RerunSink(options.sink, give_up=give_up, eager_batches=not live, keep_up=live)
    if sink.web_url:
        print(f"Rerun web viewer: {sink.web_url}", flush=True)
        print(f"swanky-host: {sink.web_note}", file=sys.stderr)
    layout = outputs.layout = start_layout(options, sink)
    dispatcher = Dispatcher(
        sink, registry=registry, config=config, strict=options.strict,
        resolver=meshes,
        on_new_topic=None if layout is None else layout.topic_seen,
    )
    if options.record_mcap is not None:
        recorder: RawOutput = McapRecorder(options.record_mcap, prefix_robot=may_hold_several_robots(
            bag=options.bag is not None,
            demo_robots=None if demo is None else len(demo.robots),
            robots=options.robots))
        outputs.recorder = recorder
        dispatcher.add_tap(recorder)
    viewer = sink.shared_viewer()
    # The converter process gets its end of a socket pair by file descriptor (POSIX).
    if live and viewer is not None and os.name == "posix":
        from host_bridge.pipeline.offload import HeavyProcess

        dispatcher.offload = outputs.offload = HeavyProcess(
            dispatcher, viewer, sink.recording_id, give_up)
    if sink.viewer_lag is not None:
        from host_bridge.pipeline.thinning import ViewerThinning, lag_path

        if outputs.offload is not None:
            heavy = outputs.offload
            sink.viewer_lag.others.append(lambda: heavy.viewer_round_trip)
        dispatcher.offload = ViewerThinning(
            dispatcher, sink, sink.viewer_lag, dispatcher.offload, stats=options.stats is not False,
            path=lag_path(options.host_name))
    if options.urdf is not None:
        log_urdf_file(options.robot, options.urdf, dispatcher)
    progress = None
    with ExitStack() as closing:
        source = open_input(
            options, dispatcher, demo=demo, robot_files=robot_files, stop=stop, closing=closing,
            bag_opener=bag_opener, layout=layout,
        )
        # The bag's extent from the input's own opening of it: rosbags parses every channel's
        # QoS when it opens an MCAP bag (nav2_turtlebot.mcap's four: 17-64 ms at load 4-5).
        extent = bag_extent(source)
        if extent is not None:
            from host_bridge.outputs.progress import Progress

            progress = Progress(extent)
            dispatcher.add_tap(progress)
        if options.slam or config.slam_configured():
            from host_bridge.slam.feeder import SlamTap

            outputs.slam = SlamTap(
                dispatcher, lambda robot: config.slam_settings(robot, options.slam),
                lossless=options.bag is not None, stop=stop, save_map=options.save_map,
                bag_types=None if extent is None else extent.types,
            )
            dispatcher.add_tap(outputs.slam)
        source.start(dispatcher.take)
        # A bag converts to its end; --duration is then how long --serve-web keeps serving it.
        wait_for_end(source, stop, options.duration if live else None,
                     options.until_idle if live else None, None if live else bag_finished(source))
    source.ended()  # what went wrong while the last items were delivered
    if outputs.slam is not None:
        outputs.slam.close()
    if progress is not None:
        progress.finish()
        if options.sink.serve_web and not stop.is_set():
            # The web viewer lives in this process: keep serving the converted bag.
            print("bag converted; serving the web viewer until Ctrl-C", file=sys.stderr)
            stop.wait(options.duration)
    dispatcher.close()
    print(dispatcher.summary(), file=sys.stderr)
    return 0
