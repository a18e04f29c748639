"""``swanky-relay``: runs on the robot; forwards raw CDR of ROS topics (live or from a bag)."""

from __future__ import annotations

import argparse
import fnmatch
import logging
import math
import os
import signal
import socket
import sys
import threading
from collections.abc import Callable, Sequence
from pathlib import Path

from robot_relay.config import RelayConfig, load_relay_config
from robot_relay.errors import RelayError
from robot_relay.session import add_zenoh_arguments, open_session, zenoh_options
from robot_relay.wire import ROBOT_NAME_PATTERN, check_robot_name

log = logging.getLogger("swanky.relay")


def default_robot_name() -> str:
    name = "".join(c if ROBOT_NAME_PATTERN.match(c) else "_" for c in socket.gethostname())
    return name or "robot"


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="swanky-relay",
        description="Forward ROS topics as raw CDR over Zenoh to a swanky-host (never decodes).",
    )
    parser.add_argument(
        "--robot", "-r",
        help="robot name: Zenoh key chunk, Rerun entity root, frame prefix (default: hostname)",
    )
    parser.add_argument(
        "--config", type=Path, metavar="RELAY.YAML",
        help="relay configuration (robot, zenoh, topics, per-topic policy; see deploy/relay.yaml); "
        "flags given here override it",
    )
    parser.add_argument("--bag", type=Path, help="replay this bag instead of the live ROS graph")
    parser.add_argument("--rate", type=float, default=1.0, help="replay speed factor (0: max)")
    parser.add_argument("--loop", action="store_true", help="replay the bag forever")
    parser.add_argument(
        "--topics", nargs="+", metavar="GLOB", help="topics to forward (globs; default: all)"
    )
    parser.add_argument(
        "--exclude", nargs="+", metavar="GLOB",
        help="topics not to forward (globs; default: hidden topics '*/_*' and /parameter_events; "
        "a topic named exactly in --topics is forwarded anyway)",
    )
    parser.add_argument(
        "--wait-for-host", type=float, default=None, metavar="SECONDS",
        help="replay: start once a host listens; give up after SECONDS (default: wait forever)",
    )
    parser.add_argument(
        "--hold", type=float, default=0.0, metavar="SECONDS",
        help="replay: afterwards keep serving latched topics (/tf_static, /robot_description, "
        "/map), the catalog and files to late hosts for SECONDS ('inf': until Ctrl-C)",
    )
    parser.add_argument(
        "--package-path", action="append", default=[], metavar="NAME=DIR",
        help="serve package://NAME/... files (meshes) from DIR to hosts (repeatable); packages "
        "a forwarded /robot_description names are also served from AMENT_PREFIX_PATH",
    )
    add_zenoh_arguments(parser)
    return parser.parse_args(argv)


def apply_config(args: argparse.Namespace, config: RelayConfig) -> None:
    """Fill what the command line left unset from the config file, then the defaults."""
    args.robot = args.robot or config.robot or default_robot_name()
    args.mode = args.mode or config.mode
    args.connect = args.connect or list(config.connect)
    args.listen = args.listen or list(config.listen)
    if not args.zenoh_config and config.zenoh_config is not None:
        args.zenoh_config = str(config.zenoh_config)
    args.no_multicast_scouting = args.no_multicast_scouting or config.multicast_scouting is False
    args.topics = args.topics or list(config.allow)
    args.exclude = list(config.deny) if args.exclude is None else args.exclude
    args.policies = config.policies


def topic_filter(include: Sequence[str], exclude: Sequence[str]) -> Callable[[str], bool]:
    """Topics matching an ``include`` glob and no ``exclude`` glob; a topic named exactly in
    ``include`` is taken whatever ``exclude`` says (asking for /parameter_events by name)."""
    named = {g for g in include if not any(c in g for c in "*?[")}

    def accept(topic: str) -> bool:
        name = "/" + topic.lstrip("/")
        return name in named or (any(fnmatch.fnmatchcase(name, g) for g in include) and not any(
            fnmatch.fnmatchcase(name, g) for g in exclude
        ))

    return accept


def run_bag(args: argparse.Namespace, stop: threading.Event) -> int:
    from robot_relay.files import serve_files
    from robot_relay.relay import Relay
    from robot_relay.sources.bag import BagSource

    with BagSource(
        args.bag, args.robot, rate=args.rate, loop=args.loop,
        topics=topic_filter(args.topics, args.exclude),
    ) as source:
        catalog = source.catalog()
        if not catalog.topics:
            log.error("bag %s has no topics matching %s", args.bag, " ".join(args.topics))
            return 1
        session = open_session(zenoh_options(args))
        try:
            relay = Relay(session, catalog, args.policies)
            files = serve_files(session, args.robot, args.package_path)
            log.info("robot %s: %d topics from %s", args.robot, len(catalog.topics), args.bag)
            if not relay.wait_for_host(args.wait_for_host):
                log.error("no host subscribed within %.1f s; nothing replayed", args.wait_for_host)
                return 1
            relay.publish_all(files.watch(source.messages()), stop)
            log.info("robot %s: replay finished, %d messages sent", args.robot, relay.published)
            if args.hold > 0 and not stop.is_set():
                log.info("robot %s: serving latched topics and files for %s s", args.robot, args.hold)
                stop.wait(None if math.isinf(args.hold) else args.hold)
            files.close()
            relay.close()
        finally:
            session.close()
    return 0


def run_live(args: argparse.Namespace, stop: threading.Event) -> int:
    from robot_relay.sources.ros2 import run_ros2_relay

    return run_ros2_relay(args, stop, topic_filter(args.topics, args.exclude))


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(levelname)s: %(message)s")
    args = parse_args(argv)
    stop = threading.Event()

    def on_signal(signum: int, frame: object) -> None:
        if stop.is_set():  # a second Ctrl-C / SIGTERM: the user does not want to wait
            print(f"swanky-relay: {signal.Signals(signum).name} again, exiting at once",
                  file=sys.stderr, flush=True)
            os._exit(128 + signum)
        log.info("%s: stopping (again to force)", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    try:
        apply_config(args, load_relay_config(args.config) if args.config else RelayConfig())
        check_robot_name(args.robot)
        return run_bag(args, stop) if args.bag is not None else run_live(args, stop)
    except RelayError as err:
        print(f"swanky-relay: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
