"""Zenoh session set-up shared by both command lines, with zenoh's own example flags
(``-m/--mode``, ``-e/--connect``, ``-l/--listen``, ``--zenoh-config`` (zenoh's ``-c/--config``:
``--config`` is each command's own YAML file), ``--cfg KEY:JSON5``,
``--no-multicast-scouting``), as in zenoh-python's examples/common/common.py."""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections.abc import Sequence

import zenoh

from robot_relay.errors import ConfigError

log = logging.getLogger("swanky.zenoh")


def add_zenoh_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("zenoh")
    group.add_argument("--mode", "-m", choices=["peer", "client", "router"], help="zenoh mode")
    group.add_argument(
        "--connect", "-e", action="append", default=[], metavar="ENDPOINT",
        help="endpoint to connect to, e.g. tcp/192.168.1.10:7447 (repeatable)",
    )
    group.add_argument(
        "--listen", "-l", action="append", default=[], metavar="ENDPOINT",
        help="endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeatable)",
    )
    group.add_argument("--zenoh-config", metavar="FILE", help="zenoh configuration file (JSON5)")
    group.add_argument(
        "--cfg", action="append", default=[], metavar="KEY:JSON5",
        help="zenoh configuration value, e.g. 'scouting/multicast/enabled:false' (repeatable)",
    )
    group.add_argument(
        "--no-multicast-scouting", action="store_true", help="disable multicast scouting"
    )


def config_from_args(args: argparse.Namespace) -> zenoh.Config:
    try:
        config: zenoh.Config = (
            zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
        )
    except Exception as err:
        msg = f"zenoh config file {args.zenoh_config}: {err}"
        raise ConfigError(msg) from err
    # zenoh-ext's AdvancedPublisher (latched topics) needs timestamps on samples.
    values: list[tuple[str, str]] = [("timestamping/enabled", "true")]
    if args.mode:
        values.append(("mode", json.dumps(args.mode)))
    if args.connect:
        values.append(("connect/endpoints", json.dumps(args.connect)))
    if args.listen:
        values.append(("listen/endpoints", json.dumps(args.listen)))
    if args.no_multicast_scouting:
        values.append(("scouting/multicast/enabled", "false"))
    for item in args.cfg:
        key, sep, value = item.partition(":")
        if not sep:
            msg = f"--cfg {item!r}: expected KEY:JSON5, e.g. 'mode:\"client\"'"
            raise ConfigError(msg)
        values.append((key, value))
    for key, value in values:
        try:
            config.insert_json5(key, value)
        except Exception as err:
            msg = f"zenoh configuration key {key!r} = {value}: {err}"
            raise ConfigError(msg) from err
    return config


def open_session(args: argparse.Namespace) -> zenoh.Session:
    config = config_from_args(args)
    try:
        session: zenoh.Session = zenoh.open(config)
    except Exception as err:
        msg = f"cannot open a zenoh session ({err}); check -e/-l endpoints, --zenoh-config and --cfg"
        raise ConfigError(msg) from err
    if args.connect:
        watch_connection(session, args.connect)
    return session


def watch_connection(
    session: zenoh.Session, endpoints: Sequence[str], after: float = 3.0
) -> threading.Thread:
    """Say clearly, once, when none of the ``-e`` endpoints answers (zenoh keeps retrying)."""

    def check() -> None:
        time.sleep(after)
        try:
            connected = session.info.peers_zid() or session.info.routers_zid()
        except Exception:  # the session closed meanwhile
            return
        if not connected:
            log.warning(
                "no zenoh peer answers at %s after %.0f s; still retrying. Is the other side "
                "running and listening there (firewall, address, port)?",
                ", ".join(endpoints), after,
            )

    thread = threading.Thread(target=check, name="zenoh-connect-watch", daemon=True)
    thread.start()
    return thread
