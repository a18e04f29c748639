"""Message definitions Swanky ships for types the bundled ROS 2 Humble store lacks.

Robots publish vision_msgs and similar packages that rosbags' Humble store does not carry; a
live source whose catalog omits the definition would otherwise be undecodable. The texts live
in ``schemas/msg/<pkg>/<Name>.msg`` of the repository (language-neutral, reviewable; installed as
the data package ``swanky_schemas``), and the decoder registers them into its base typestore.

Robots on rmw_zenoh send no definitions, only a type hash: :class:`BundledDefinitions` picks the
bundled definition (Humble, else Jazzy) that hash names.
"""

from __future__ import annotations

import threading
from importlib.resources import files
from pathlib import Path

from rosbags.interfaces.typing import Typesdict
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.errors import UnknownTypeError
from robot_relay.wire import MessageDefinition

MSG_DIR = Path(str(files("swanky_schemas") / "msg"))


def extra_typesdict(root: Path = MSG_DIR) -> Typesdict:
    """Every ``<root>/<pkg>/<Name>.msg`` parsed as ``<pkg>/msg/<Name>``.

    Types they use from other packages (std_msgs/Header, geometry_msgs/Pose) are referenced,
    not included: register the result into a store that already holds them.
    """
    types: Typesdict = {}
    for path in sorted(root.glob("*/*.msg")):
        name = f"{path.parent.name}/msg/{path.stem}"
        try:
            types.update(get_types_from_msg(path.read_text(encoding="utf-8"), name))
        except Exception as err:
            msg = f"bundled definition {path} of {name!r} does not parse: {err}"
            raise UnknownTypeError(msg) from err
    return types


def base_typestore() -> Typestore:
    """ROS 2 Humble plus the definitions shipped in schemas/msg (vision_msgs, ...): what the
    decoder starts from."""
    store = get_typestore(Stores.ROS2_HUMBLE)
    store.register(extra_typesdict())
    return store


class BundledDefinitions:
    """Which bundled definition a publisher's type hash names: Humble (plus schemas/msg),
    else Jazzy. ``None`` means "the decoder's own bundled Humble store"."""

    def __init__(self) -> None:
        self._answers: dict[tuple[str, str], tuple[MessageDefinition | None, str | None]] = {}
        self._lock = threading.Lock()

    def lookup(self, msgtype: str, type_hash: str | None) -> tuple[MessageDefinition | None, str | None]:
        """(definition to decode with, warning to show once or None)."""
        if type_hash is None:
            return None, None
        with self._lock:
            answer = self._answers.get((msgtype, type_hash))
            if answer is None:
                answer = self._answers[(msgtype, type_hash)] = self._match(msgtype, type_hash)
        return answer

    @staticmethod
    def _match(msgtype: str, type_hash: str) -> tuple[MessageDefinition | None, str | None]:
        humble = base_typestore()
        for index, store in enumerate((humble, get_typestore(Stores.ROS2_JAZZY))):
            if msgtype not in store.fielddefs:
                continue
            try:
                matches = store.hash_rihs01(msgtype) == type_hash
            except Exception:  # a definition rosbags cannot hash: not this one
                matches = False
            if matches:
                if index == 0:
                    return None, None
                return MessageDefinition("ros2msg", store.generate_msgdef(msgtype, ros_version=2)[0]), None
        if msgtype in humble.fielddefs:
            return None, (
                f"type hash {type_hash} of {msgtype} matches no bundled definition (Humble, "
                "Jazzy): decoding with the Humble one, which fails if the layouts differ"
            )
        return None, None  # unknown type: the decoder names it, once per topic
