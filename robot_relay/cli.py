"""``swanky-relay``: runs on the robot; forwards raw CDR of ROS topics (live or from a bag).

This module only turns flags (over the ``--config`` file) into a
:class:`~robot_relay.app.RelayOptions` record and the process's signals into a stop event;
``robot_relay/app.py`` does the rest."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import math
import os
import socket
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from robot_relay import app
from robot_relay.config import RelayConfig, load_relay_config
from robot_relay.errors import RelayError
from robot_relay.session import add_zenoh_arguments, zenoh_options
from robot_relay.signals import StopSignals
from robot_relay.sources.take_loop import LATENCY_BUDGET_S, MAX_LATENCY_BUDGET_S
from robot_relay.wire import ROBOT_NAME_PATTERN

STOP_DEADLINE_S = 15.0
"""A relay still stopping this long after the signal prints every thread's stack and exits
(the relay holds nothing a forced exit loses; a library call that never returns must not keep
the robot's relay alive)."""

log = logging.getLogger("swanky.relay")


def default_robot_name() -> str:
    name = "".join(c if ROBOT_NAME_PATTERN.match(c) else "_" for c in socket.gethostname())
    return name or "robot"


def latency_budget(text: str) -> float:
    """``--latency-budget``: seconds, 0 to 1 (more is surely milliseconds meant as seconds)."""
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not 0.0 <= value <= MAX_LATENCY_BUDGET_S:
        msg = f"{text!r} is not a number of seconds from 0 to {MAX_LATENCY_BUDGET_S:g}"
        raise argparse.ArgumentTypeError(msg)
    return value


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
    parser.add_argument(
        "--latency-budget", type=latency_budget, default=None, metavar="SECONDS",
        help="live: the longest a message may wait so that messages close together are taken "
        f"and sent with one wake-up, less CPU on the robot (default {LATENCY_BUDGET_S}; 0: "
        "forward each message at once)",
    )
    add_zenoh_arguments(parser)
    return parser.parse_args(argv)


def relay_options(args: argparse.Namespace, config: RelayConfig) -> app.RelayOptions:
    """The flags over the ``--config`` file (what the command line left unset comes from the
    file, then the defaults)."""
    zenoh = zenoh_options(args)
    return app.RelayOptions(
        robot=args.robot or config.robot or default_robot_name(),
        zenoh=dataclasses.replace(
            zenoh,
            mode=zenoh.mode or config.mode,
            connect=zenoh.connect or config.connect,
            listen=zenoh.listen or config.listen,
            config_file=zenoh.config_file or (
                None if config.zenoh_config is None else str(config.zenoh_config)
            ),
            multicast_scouting=zenoh.multicast_scouting and config.multicast_scouting is not False,
        ),
        topics=tuple(args.topics or config.allow),
        exclude=config.deny if args.exclude is None else tuple(args.exclude),
        policies=config.policies,
        bag=args.bag,
        rate=args.rate,
        loop=args.loop,
        wait_for_host=args.wait_for_host,
        hold=args.hold,
        package_path=tuple(args.package_path),
        latency_budget=next(budget for budget in (
            args.latency_budget, config.latency_budget, LATENCY_BUDGET_S
        ) if budget is not None),
    )


def main(argv: Sequence[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(levelname)s: %(message)s")
    args = parse_args(argv)
    signals = StopSignals("swanky-relay", log, deadline_s=STOP_DEADLINE_S)
    signals.install()
    try:
        config = load_relay_config(args.config) if args.config else RelayConfig()
        return app.run(relay_options(args, config), signals.stop)
    except RelayError as err:
        print(f"swanky-relay: error: {err}", file=sys.stderr)
        return 2
    finally:
        signals.cancel_deadline()


def console_main() -> NoReturn:
    """The ``swanky-relay`` command: :func:`main`, then out of the process without finalizing
    Python. Zenoh's and ROS's own threads may still call into Python while it finalizes (a last
    matching, liveliness or graph callback); CPython then ends such a thread by unwinding it,
    which their Rust or C++ frames turn into an abort ("FATAL: exception not rethrown", exit -6:
    seen under load when SIGTERM stopped a live relay). By then everything is closed."""
    code = main()
    logging.shutdown()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    console_main()
