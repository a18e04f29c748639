"""CDR -> Python message objects with rosbags, from the definitions the input carried.

Each distinct (type, definition text) gets its own typestore: a ROS 1 bag's CameraInfo (``D K R
P``, ``Header.seq``) and a Humble CameraInfo may both be on the same host at once, and rosbags
refuses to register two definitions of one name in a store. Types without a definition (a
Humble sqlite3 bag stores none) come from the bundled ROS 2 Humble store plus ``schemas/msg``.

Service events (``/<service>/_service_event`` topics, type ``<pkg>/srv/<Name>_Event``, recorded
from Iron on) carry the *service's* definition, rosbag2's ``SRV:`` block with request ``---``
response, which rosbags' parser does not read. The event message rosidl generates from it is
``service_msgs/ServiceEventInfo info``, ``<Name>_Request[<=1] request``, ``<Name>_Response[<=1]
response``; :func:`service_event_types` builds exactly that.
"""

from __future__ import annotations

import functools
from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.core.schemas import base_typestore
from host_bridge.errors import DecodeError, UnknownTypeError
from robot_relay.wire import MessageDefinition, RawMessage

IDL_SEPARATOR = "=" * 80 + "\n"
SERVICE_EVENT_SUFFIX = "_Event"
SERVICE_EVENT_INFO = "service_msgs/msg/ServiceEventInfo"


def is_service_event_type(msgtype: str) -> bool:
    """``<pkg>/srv/<Name>_Event``, the type of a ``/<service>/_service_event`` topic."""
    parts = msgtype.split("/")
    return len(parts) == 3 and parts[1] == "srv" and parts[2].endswith(SERVICE_EVENT_SUFFIX)


def service_type(event_type: str) -> str:
    """``example_interfaces/srv/AddTwoInts`` of ``example_interfaces/srv/AddTwoInts_Event``."""
    return event_type[: -len(SERVICE_EVENT_SUFFIX)]


def service_event_types(
    event_type: str, request: tuple[Any, Any], response: tuple[Any, Any]
) -> dict[str, Any]:
    """Field tables of a service event and of its request and response messages."""
    service = service_type(event_type)

    def at_most_one(name: str) -> tuple[Nodetype, Any]:
        return (Nodetype.SEQUENCE, ((Nodetype.NAME, name), 1))

    return {
        f"{service}_Request": request,
        f"{service}_Response": response,
        event_type: ([], [
            ("info", (Nodetype.NAME, SERVICE_EVENT_INFO)),
            ("request", at_most_one(f"{service}_Request")),
            ("response", at_most_one(f"{service}_Response")),
        ]),
    }


def _idl_types(body: str) -> dict[str, Any]:
    # rosbags' IDL grammar has no preprocessor; the blocks already carry what #include pulls in.
    lines = (line for line in body.split("\n") if not line.startswith("#include"))
    return dict(get_types_from_idl("\n".join(lines)))


def _block_types(kind: str, name: str, body: str, msgtype: str) -> dict[str, Any]:
    """Types of one block of rosbag2's delimited definition text (``MSG:``/``IDL:``/``SRV:``)."""
    if kind == "IDL":
        return _idl_types(body)
    if kind == "MSG":
        # A dependency found only as .idl gets an empty MSG block before its IDL block.
        return dict(get_types_from_msg(body, name)) if body.strip() else {}
    if kind == "SRV" and is_service_event_type(msgtype):
        lines = body.split("\n")
        split = next((i for i, line in enumerate(lines) if line.strip() == "---"), None)
        if split is None:
            msg = f"SRV block of {name} has no '---' line between request and response"
            raise UnknownTypeError(msg)
        # Parsed under a msg/ name, so the srv's own package types (bare names) resolve to
        # <pkg>/msg/<Type> as they do in ROS.
        package, _, service = name.split("/")
        halves = {"Request": lines[:split], "Response": lines[split + 1 :]}
        parsed = {}
        for part, text in halves.items():
            msg_name = f"{package}/msg/{service}_{part}"
            parsed[part] = get_types_from_msg("\n".join(text), msg_name)[msg_name]
        return service_event_types(msgtype, parsed["Request"], parsed["Response"])
    msg = f"a {kind}: block ({name}) is not a message definition rosbag2 writes for {msgtype}"
    raise UnknownTypeError(msg)


def _parse(definition: MessageDefinition, msgtype: str) -> dict[str, Any]:
    if not definition.text.startswith(IDL_SEPARATOR):
        if definition.encoding == "ros2idl":
            return _idl_types(definition.text)
        return dict(get_types_from_msg(definition.text, msgtype))
    # rosbag2's delimited form: one "KIND: pkg/msg/Name" block per file (IDL roots, services).
    types: dict[str, Any] = {}
    for block in definition.text.split(IDL_SEPARATOR)[1:]:
        header, _, body = block.partition("\n")
        kind, _, name = header.partition(": ")
        types.update(_block_types(kind, name.strip(), body, msgtype))
    return types


def _as_service_event(msgtype: str, problem: str) -> str:
    """Why a type cannot be decoded, saying what a service event topic is when it is one."""
    if not is_service_event_type(msgtype):
        return problem
    return (
        f"service events of {service_type(msgtype)} (the requests and responses rosbag2 "
        f"records with --services) are skipped: {problem}"
    )


def _no_definition(msgtype: str) -> str:
    """Why a type the source sent no definition for, and the bundled store lacks, is lost."""
    if is_service_event_type(msgtype):
        return _as_service_event(msgtype, (
            f"no definition of {msgtype} came with them (rosbag2 stores none when it finds no "
            ".srv file for the service while recording)"
        ))
    return (
        f"type {msgtype} has no definition: the source sent none (a rosbag2 recorded before "
        "Iron, like Humble's sqlite3 bags, stores none) and it is neither a ROS 2 Humble type "
        "nor one bundled in schemas/msg (add its .msg there, or record with Iron or later)"
    )


def _referenced_types(fielddefs: dict[str, Any]) -> set[str]:
    """Names of every message type the parsed definitions refer to."""
    names: set[str] = set()

    def walk(desc: Any) -> None:
        kind, arg = desc
        if kind == Nodetype.NAME:
            names.add(arg)
        elif kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            walk(arg[0])

    for _, fields in fielddefs.values():
        for _, desc in fields:
            walk(desc)
    return names


class Decoder:
    """Deserializes RawMessages; caches one typestore per distinct definition (and the error of
    one that cannot be used, so a bad topic costs one parse, not one per message)."""

    def __init__(self, base: Typestore | None = None) -> None:
        self._given_base = base
        # A str is why that definition cannot be used (a fresh error is raised from it each time:
        # re-raising one exception object would grow its traceback message after message).
        self._stores: dict[tuple[str, MessageDefinition | None], Typestore | str] = {}

    @functools.cached_property
    def _base(self) -> Typestore:
        """Built when first needed (a type without a definition, or a definition that leaves a
        dependency out): loading ROS 2 Humble's types takes 0.15 to 0.25 s, which bags and robots
        sending complete definitions never need."""
        return self._given_base or base_typestore()

    def typestore_for(self, msgtype: str, definition: MessageDefinition | None) -> Typestore:
        if definition is None and msgtype in self._base.fielddefs:
            return self._base
        key = (msgtype, definition)
        store = self._stores.get(key)
        if store is None:
            try:
                store = self._build(msgtype, definition)
            except UnknownTypeError as err:
                store = str(err)
            self._stores[key] = store
        if isinstance(store, str):
            raise UnknownTypeError(store)
        return store

    def _build(self, msgtype: str, definition: MessageDefinition | None) -> Typestore:
        if definition is None:
            raise UnknownTypeError(_no_definition(msgtype))
        try:
            types = _parse(definition, msgtype)
        except Exception as err:
            msg = f"definition of {msgtype!r} ({definition.encoding}) does not parse: {err}"
            raise UnknownTypeError(_as_service_event(msgtype, msg)) from err
        if msgtype not in types:
            msg = f"definition sent for {msgtype!r} does not define that type"
            raise UnknownTypeError(_as_service_event(msgtype, msg))
        # Fill dependencies the text left out (e.g. builtin_interfaces) from the bundled store.
        missing = _referenced_types(types) - types.keys()
        while missing:
            unknown = missing - self._base.fielddefs.keys()
            if unknown:
                msg = f"definition of {msgtype!r} uses {sorted(unknown)} which nothing defines"
                raise UnknownTypeError(_as_service_event(msgtype, msg))
            added = {name: self._base.fielddefs[name] for name in missing}
            types.update(added)
            missing = _referenced_types(added) - types.keys()
        store = get_typestore(Stores.EMPTY)
        store.register(types)
        return store

    def decode(self, raw: RawMessage) -> Any:
        store = self.typestore_for(raw.msgtype, raw.definition)
        try:
            return store.deserialize_cdr(raw.data, raw.msgtype)
        except Exception as err:
            msg = (
                f"{len(raw.data)}-byte {raw.msgtype} payload does not deserialize "
                f"(truncated, or not the type the source announced): {err}"
            )
            raise DecodeError(msg) from err
