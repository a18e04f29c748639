"""Zenoh session set-up shared by both command lines, with zenoh's own example flags
(``-m/--mode``, ``-e/--connect``, ``-l/--listen``, ``--zenoh-config`` (zenoh's ``-c/--config``:
``--config`` is each command's own YAML file), ``--cfg KEY:JSON5``,
``--no-multicast-scouting``), as in zenoh-python's examples/common/common.py.

Priority links (``--priority-links``, off by default): one TCP connection carries everything in
order, so on a slow link the images fill its kernel send buffer and a 1 KB odometry message
waits behind seconds of them, whatever Zenoh's priorities say (they only order what is still in
Zenoh's own queues). With priority links each ``tcp/`` or ``tls/`` endpoint the command connects
to is opened as two links of one Zenoh transport (zenoh 1.x endpoint metadata ``?prio=``):
``data_low`` and ``background`` (images, clouds, video: :mod:`robot_relay.policy`) on one,
everything else on the other. ``transport/unicast/max_links`` is raised to 2, flag or not, so a listening
host or router accepts the second link (a one-link peer refuses it; the first then carries every
priority). Off by default because zenoh sends a priority on whichever link exists while its own
is missing, and its receiver drops, unannounced, a reliable message that arrives after a later
one of its priority (zenoh-transport's ``verify_sn``): when the second link comes up late (a SYN
lost on a lossy link) or one breaks, reliable messages in flight on the old link can be lost."""

from __future__ import annotations

import argparse
import json
import logging
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import zenoh

from robot_relay.errors import ConfigError

log = logging.getLogger("swanky.zenoh")


@dataclass(frozen=True, slots=True)
class ZenohOptions:
    """How to open the Zenoh session: the zenoh flags both commands take, as a record (what
    ``open_session`` reads, so nothing below the command lines sees ``argparse``)."""

    mode: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str | None = None
    """``--zenoh-config``: a zenoh configuration file (JSON5)."""
    cfg: tuple[str, ...] = ()
    """``--cfg KEY:JSON5`` items, applied last."""
    multicast_scouting: bool = True
    priority_links: bool = False
    """Connect to each ``tcp/``/``tls/`` endpoint with a bulk and a priority link (module doc)."""


PRIORITY_RANGES = ("0-5", "6-7")
"""Zenoh priorities by number (0 control ... 5 data; 6 data_low, 7 background), one range per
link: control and ``real_time`` ... ``data`` on the first, bulk on the second."""
STREAM_SCHEMES = ("tcp", "tls")
"""Link protocols whose single byte stream makes small messages wait behind large ones."""


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
    group.add_argument(
        "--priority-links", action="store_true",
        help="two TCP/TLS connections per -e endpoint: one for data_low/background topics "
        "(images, clouds), one for the rest, so small topics keep flowing when a slow link is "
        "full of images; a reliable message in flight when a link comes or goes can be lost",
    )


def zenoh_options(args: argparse.Namespace) -> ZenohOptions:
    """The record of the flags :func:`add_zenoh_arguments` added (each command's cli.py)."""
    return ZenohOptions(
        mode=args.mode,
        connect=tuple(args.connect),
        listen=tuple(args.listen),
        config_file=args.zenoh_config,
        cfg=tuple(args.cfg),
        multicast_scouting=not args.no_multicast_scouting,
        priority_links=args.priority_links,
    )


def priority_link_endpoints(endpoint: str) -> tuple[str, ...]:
    """``endpoint`` as one endpoint per :data:`PRIORITY_RANGES` (``tcp/pc:7447`` ->
    ``tcp/pc:7447?prio=0-5``, ``tcp/pc:7447?prio=6-7``), other metadata and ``#`` link
    configuration kept; as given when it is not TCP/TLS or already names its priorities."""
    address, hash_sign, link_config = endpoint.partition("#")
    locator, _, metadata = address.partition("?")
    keys = {item.partition("=")[0] for item in metadata.split(";") if item}
    if endpoint.partition("/")[0] not in STREAM_SCHEMES or "prio" in keys:
        return (endpoint,)
    return tuple(
        f"{locator}?{';'.join([*([metadata] if metadata else []), f'prio={priorities}'])}"
        f"{hash_sign}{link_config}"
        for priorities in PRIORITY_RANGES
    )


def zenoh_config(options: ZenohOptions) -> zenoh.Config:
    try:
        config: zenoh.Config = (
            zenoh.Config.from_file(options.config_file) if options.config_file else zenoh.Config()
        )
    except Exception as err:
        msg = f"zenoh config file {options.config_file}: {err}"
        raise ConfigError(msg) from err
    # zenoh-ext's AdvancedPublisher (latched topics) needs timestamps on samples.
    values: list[tuple[str, str]] = [("timestamping/enabled", "true")]
    if options.mode:
        values.append(("mode", json.dumps(options.mode)))
    connect = list(options.connect)
    if options.priority_links:
        connect = [split for endpoint in connect for split in priority_link_endpoints(endpoint)]
    # Always: a host or relay listening accepts a peer's priority links without a flag of its own.
    max_links = json.loads(config.get_json("transport/unicast/max_links"))
    values.append(("transport/unicast/max_links", str(max(max_links, len(PRIORITY_RANGES)))))
    if connect:
        values.append(("connect/endpoints", json.dumps(connect)))
    if options.listen:
        values.append(("listen/endpoints", json.dumps(list(options.listen))))
    if not options.multicast_scouting:
        values.append(("scouting/multicast/enabled", "false"))
    for item in options.cfg:
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


def open_session(options: ZenohOptions) -> zenoh.Session:
    config = zenoh_config(options)
    try:
        session: zenoh.Session = zenoh.open(config)
    except Exception as err:
        msg = f"cannot open a zenoh session ({err}); check -e/-l endpoints, --zenoh-config and --cfg"
        raise ConfigError(msg) from err
    if options.connect:
        watch_connection(session, options.connect)
    optimization = "transport/shared_memory/transport_optimization"
    if all(json.loads(config.get_json(key)) for key in (
        "transport/shared_memory/enabled", f"{optimization}/enabled"
    )):
        _POOLS[str(session.zid())] = SharedMemoryPool(
            json.loads(config.get_json(f"{optimization}/pool_size"))
        )
    return session


LARGE_PAYLOAD_BYTES = 65_536
"""From this size on (a payload Zenoh would fragment on a network link) the relay writes a
payload straight into shared memory (:class:`SharedMemoryPool`)."""


class SharedMemoryPool:
    """Large payloads written straight into a shared-memory buffer: one copy fewer for a host
    on the same machine, none more for a remote one.

    Zenoh hands a payload above its ``transport_optimization`` threshold to a peer on the same
    machine through shared memory, but zenoh-python first copies the ``bytes`` into a buffer of
    its own and zenoh then copies that into its pool: two copies of every image, the relay's
    main cost at 1 MB (70 % of its CPU in ``memmove``, perf). Written into a pool buffer here,
    it is one, and Zenoh sends the buffer as it is: a reference to a peer on this machine, its
    bytes to any other (what ``bytes`` would cost). Buffers the readers released are reclaimed
    before each allocation, so recently written ones, still in the CPU cache, are written again:
    reclaiming only once the pool is full (zenoh's own ``GarbageCollect`` policy) cycles through
    all of it and cost a remote host's payloads 19-38 % more user CPU. Measured with 1 MB
    payloads on loopback, 6 interleaved rounds (the processes of
    ``benchmarks/relay_throughput.py``): with a shared-memory subscriber the relay takes 104 us
    of CPU per message, a bare publisher of ``bytes`` 169 (the relay without the pool as much
    as the bare one, within this machine's noise); with a subscriber without shared memory, as
    a remote host is, 741 with the pool and 740 without.

    The pool is made on the first large payload, as large as Zenoh's own
    (``transport/shared_memory/transport_optimization/pool_size``, 16 MiB by default); while it
    is full (readers still hold its buffers) or when shared memory is unavailable, payloads go
    as ``bytes``.
    """

    def __init__(self, size: int) -> None:
        self._size = size
        self._lock = threading.Lock()
        self._provider: Any = None
        self._unavailable = False

    def copy(self, payload: bytes) -> Any | None:
        """``payload`` in a shared-memory buffer (a ``zenoh.shm.ZShmMut``, for ``put``), or
        None: below :data:`LARGE_PAYLOAD_BYTES`, the pool full or shared memory unavailable."""
        if len(payload) < LARGE_PAYLOAD_BYTES or (self._provider is None and not self._open()):
            return None
        self._provider.garbage_collect()
        try:
            buffer = self._provider.alloc(len(payload))
        except zenoh.ZError:  # full: the readers still hold every buffer large enough
            return None
        buffer[:] = payload
        return buffer

    def _open(self) -> bool:
        with self._lock:
            if self._provider is None and not self._unavailable:
                try:
                    self._provider = zenoh.shm.ShmProvider.default_backend(self._size)
                except (zenoh.ZError, AttributeError) as err:  # no /dev/shm, a zenoh without SHM
                    self._unavailable = True
                    log.info("large payloads go without shared memory: %s", err)
            return self._provider is not None


_POOLS: dict[str, SharedMemoryPool] = {}
"""The shared-memory pool of each session :func:`open_session` opened with Zenoh's shared
memory on, by session id, until :func:`close_session`."""


def shared_memory_pool(session: zenoh.Session) -> SharedMemoryPool | None:
    """Where ``session``'s publishers write large payloads; None when it has no pool (shared
    memory off in its configuration, or not opened by :func:`open_session`)."""
    return _POOLS.get(str(session.zid()))


def close_session(session: zenoh.Session) -> None:
    """Close ``session``. Zenoh gives up closing after a timeout when a peer stopped answering
    (a link cut, Wi-Fi out of range) and raises; that is said, not raised, so the command still
    ends cleanly and whatever it saved is complete."""
    _POOLS.pop(str(session.zid()), None)
    try:
        session.close()
    except zenoh.ZError as err:
        log.warning("the zenoh session did not close cleanly (%s): a peer stopped answering", err)


def watch_connection(
    session: zenoh.Session, endpoints: Sequence[str], after: float = 3.0
) -> threading.Thread:
    """Say clearly, once, when none of the ``-e`` endpoints answers (zenoh keeps retrying)."""

    def check() -> None:
        time.sleep(after)
        try:
            # A session closed meanwhile has no peers either: nothing to say then.
            connected = session.is_closed() or session.info.peers_zid() or session.info.routers_zid()
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
