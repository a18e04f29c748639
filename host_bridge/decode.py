"""CDR -> Python message objects with rosbags, from the definitions the input carried.

Each distinct (type, definition text) gets its own typestore: a ROS 1 bag's CameraInfo (``D K R
P``, ``Header.seq``) and a Humble CameraInfo may both be on the same host at once, and rosbags
refuses to register two definitions of one name in a store. Types without a definition come
from the bundled ROS 2 Humble store.
"""

from __future__ import annotations

from typing import Any

from rosbags.interfaces import Nodetype
from rosbags.typesys import Stores, get_types_from_idl, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.errors import DecodeError, UnknownTypeError
from robot_relay.wire import MessageDefinition, RawMessage


def base_typestore() -> Typestore:
    """ROS 2 Humble plus the definitions shipped in schemas/msg (vision_msgs, ...)."""
    from host_bridge.schemas import extra_typesdict

    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(extra_typesdict())
    return store


IDL_SEPARATOR = "=" * 80 + "\n"


def _parse(definition: MessageDefinition, msgtype: str) -> dict[str, Any]:
    if definition.encoding != "ros2idl":
        return dict(get_types_from_msg(definition.text, msgtype))
    if not definition.text.startswith(f"{IDL_SEPARATOR}IDL: "):
        return dict(get_types_from_idl(definition.text))
    # rosbag2's delimited form: one "IDL: pkg/msg/Name" block per file, as AnyReader reads it.
    # rosbags' IDL grammar has no preprocessor; the blocks already carry what #include pulls in.
    types: dict[str, Any] = {}
    for block in definition.text.split(IDL_SEPARATOR)[1:]:
        _, body = block.split("\n", 1)
        lines = (line for line in body.split("\n") if not line.startswith("#include"))
        types.update(get_types_from_idl("\n".join(lines)))
    return types


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
    """Deserializes RawMessages; caches one typestore per distinct definition."""

    def __init__(self, base: Typestore | None = None) -> None:
        self._base = base or base_typestore()
        self._stores: dict[tuple[str, MessageDefinition], Typestore] = {}

    def typestore_for(self, msgtype: str, definition: MessageDefinition | None) -> Typestore:
        if definition is None:
            if msgtype not in self._base.fielddefs:
                msg = (
                    f"no definition for type {msgtype!r}: it is not a ROS 2 Humble type and the "
                    "source sent none (add its .msg to schemas/msg or let the relay's catalog "
                    "carry it)"
                )
                raise UnknownTypeError(msg)
            return self._base
        key = (msgtype, definition)
        store = self._stores.get(key)
        if store is None:
            store = self._build(msgtype, definition)
            self._stores[key] = store
        return store

    def _build(self, msgtype: str, definition: MessageDefinition) -> Typestore:
        try:
            types = _parse(definition, msgtype)
        except Exception as err:
            msg = f"definition of {msgtype!r} ({definition.encoding}) does not parse: {err}"
            raise UnknownTypeError(msg) from err
        if msgtype not in types:
            msg = f"definition sent for {msgtype!r} does not define that type"
            raise UnknownTypeError(msg)
        # Fill dependencies the text left out (e.g. builtin_interfaces) from the bundled store.
        missing = _referenced_types(types) - types.keys()
        while missing:
            unknown = missing - self._base.fielddefs.keys()
            if unknown:
                msg = f"definition of {msgtype!r} uses {sorted(unknown)} which nothing defines"
                raise UnknownTypeError(msg)
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
