"""Message definitions Swanky ships for types the bundled ROS 2 Humble store lacks.

Robots publish vision_msgs and similar packages that rosbags' Humble store does not carry; a
live source whose catalog omits the definition would otherwise be undecodable. The texts live
in ``schemas/msg/<pkg>/<Name>.msg`` of the repository (language-neutral, reviewable; installed as
the data package ``swanky_schemas``), and the decoder registers them into its base typestore.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

from rosbags.interfaces.typing import Typesdict
from rosbags.typesys import get_types_from_msg

from host_bridge.errors import UnknownTypeError

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
