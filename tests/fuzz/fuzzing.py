"""What the fuzz tests share: reproducible, bounded Hypothesis settings, the ways a message goes
bad on the way (cut short, grown, bytes flipped, a length prefix made huge), and messages of any
bundled type whose fields hold odd values.

``derandomize`` and no example database make every run try the same inputs, so CI fails the same
way on every machine; the example counts keep the whole fuzz set well under a minute on a loaded
2-core machine, and the deadline is generous for the same reason (a slow example is not a bug).

Bad messages are built from :class:`Choices`: Hypothesis' draws in the property tests
(:func:`mutated`, :func:`payloads`: shrunk when they fail), or a seeded ``random.Random``
(:class:`Seeded`) where thousands are needed at once (a flood of garbage on a robot's keys):
Hypothesis takes 10 ms or more per example on a loaded machine.
"""

from __future__ import annotations

import datetime
import math
import random
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import numpy as np
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st
from rosbags.interfaces import Nodetype

from host_bridge.core.schemas import base_typestore

FUZZ = settings(
    derandomize=True,
    database=None,
    max_examples=300,
    deadline=datetime.timedelta(seconds=5),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

# Values a u32 length prefix is set to: each claims more than any payload holds.
HUGE_U32 = (0x7FFFFFFF, 0xFFFFFFFF, 0x10000000, 1_000_000_000)

STORE = base_typestore()
"""The types a host knows without a definition sent: ROS 2 Humble and schemas/msg."""

T = TypeVar("T")


class Choices(Protocol):
    """Where a bad message's choices come from."""

    def pick(self, options: Sequence[T]) -> T: ...
    def integer(self, low: int, high: int) -> int: ...
    def boolean(self) -> bool: ...
    def binary(self, min_size: int, max_size: int) -> bytes: ...


@dataclass(frozen=True, slots=True)
class Drawn:
    """Choices drawn by Hypothesis, inside an ``st.composite``."""

    draw: st.DrawFn

    def pick(self, options: Sequence[T]) -> T:
        return self.draw(st.sampled_from(options))

    def integer(self, low: int, high: int) -> int:
        return self.draw(st.integers(low, high))

    def boolean(self) -> bool:
        return self.draw(st.booleans())

    def binary(self, min_size: int, max_size: int) -> bytes:
        return self.draw(st.binary(min_size=min_size, max_size=max_size))


@dataclass(frozen=True, slots=True)
class Seeded:
    """Choices of a seeded ``random.Random``: the same on every run, thousands a second."""

    rng: random.Random

    def pick(self, options: Sequence[T]) -> T:
        return self.rng.choice(options)

    def integer(self, low: int, high: int) -> int:
        return self.rng.randint(low, high)

    def boolean(self) -> bool:
        return self.rng.random() < 0.5

    def binary(self, min_size: int, max_size: int) -> bytes:
        return self.rng.randbytes(self.rng.randint(min_size, max_size))


def mutation(data: bytes, choose: Choices) -> bytes:
    """``data`` gone bad in one of the ways a link, a disk or an attacker makes it."""
    size = len(data)
    kind = choose.pick(["truncate", "extend", "flip", "huge_u32", "random"])
    if kind == "truncate":
        # Each length class: empty, inside the 4-byte CDR header, just after it, the middle,
        # one byte short.
        return data[:choose.pick(sorted({0, 1, 3, 4, 5, 8, size // 2, max(size - 1, 0)}))]
    if kind == "extend":
        return data + choose.binary(1, 64)
    if kind == "flip" and size:
        out = bytearray(data)
        for _ in range(choose.integer(1, 8)):
            out[choose.integer(0, size - 1)] ^= choose.integer(1, 255)
        return bytes(out)
    if kind == "huge_u32" and size >= 8:
        # A CDR sequence/string length (u32, 4-aligned after the 4-byte header) made huge.
        at = 4 + 4 * choose.integer(0, (size - 8) // 4)
        out = bytearray(data)
        out[at:at + 4] = choose.pick(HUGE_U32).to_bytes(4, "little")
        return bytes(out)
    return choose.binary(0, max(size, 16))


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """:func:`mutation` drawn by Hypothesis."""
    return mutation(data, Drawn(draw))


_FLOATS = [0.0, 1.0, -2.5, 0.05, math.nan, math.inf, -math.inf, 1e30, -1e-30, 3.0e38]
_INT_RANGES = {
    "int8": (-(2**7), 2**7 - 1), "int16": (-(2**15), 2**15 - 1),
    "int32": (-(2**31), 2**31 - 1), "int64": (-(2**63), 2**63 - 1),
    "uint8": (0, 2**8 - 1), "byte": (-(2**7), 2**7 - 1), "char": (0, 2**8 - 1), "octet": (0, 2**8 - 1),
    "uint16": (0, 2**16 - 1), "uint32": (0, 2**32 - 1), "uint64": (0, 2**64 - 1),
}
_STRINGS = ["", "map", "base_link", "rgb8", "16UC1", "32FC1", "jpeg", "png", "compressedDepth png",
            "h264", "xyz", "x", "rgb", "intensity", "é/../ x", "a" * 300]
# numpy's dtype of each ROS type rosbags serializes (its "byte" is numpy's signed byte).
_DTYPES = {"bool": "bool", "byte": "int8", "char": "uint8", "octet": "uint8"}


def _number(ros_type: str, choose: Choices) -> Any:
    if ros_type in ("float32", "float64"):
        return choose.pick(_FLOATS)
    if ros_type == "bool":
        return choose.boolean()
    low, high = _INT_RANGES[ros_type]
    # The extremes, small counts, and the sizes a hostile header declares (10^5, 10^9).
    return choose.pick(sorted({v for v in (low, high, 0, 1, 2, 3, 4, 16, 100_000, 10**9)
                               if low <= v <= high}))


def _values(desc: tuple[Any, Any], count: int, choose: Choices) -> Any:
    """``count`` values of one field type: a numpy array for numbers (what rosbags serializes),
    a list otherwise."""
    kind, arg = desc
    if kind == Nodetype.BASE and arg[0] != "string":
        ros_type = arg[0]
        dtype = _DTYPES.get(ros_type, ros_type)
        if dtype == "uint8" and choose.boolean():
            return np.frombuffer(choose.binary(count, count), np.uint8)
        return np.array([_number(ros_type, choose) for _ in range(count)], dtype=dtype)
    return [_field(desc, choose) for _ in range(count)]


def _field(desc: tuple[Any, Any], choose: Choices) -> Any:
    kind, arg = desc
    if kind == Nodetype.BASE:
        return choose.pick(_STRINGS) if arg[0] == "string" else _number(arg[0], choose)
    if kind == Nodetype.NAME:
        return message(arg, choose)
    if kind == Nodetype.ARRAY:
        return _values(arg[0], arg[1], choose)
    # SEQUENCE: short, or (for byte data) up to 64 bytes.
    return _values(arg[0], choose.integer(0, 3 if arg[0][0] == Nodetype.NAME else 64), choose)


def message(msgtype: str, choose: Choices) -> Any:
    """A ``msgtype`` message (a type of :data:`STORE`) whose fields hold odd values: NaN,
    infinities, extreme integers, declared sizes of 10^9, odd strings."""
    _, fields = STORE.fielddefs[msgtype]
    return STORE.types[msgtype](**{name: _field(desc, choose) for name, desc in fields})


def bad_payload(msgtype: str, choose: Choices) -> tuple[bytes, str]:
    """The CDR of a :func:`message` of ``msgtype``, as is or gone bad on the way
    (:func:`mutation`), and which of the two."""
    cdr = bytes(STORE.serialize_cdr(message(msgtype, choose), msgtype))
    if choose.boolean():
        return cdr, "odd fields"
    return mutation(cdr, choose), "mutated bytes"


@st.composite
def payloads(draw: st.DrawFn, msgtype: str) -> tuple[bytes, str]:
    """:func:`bad_payload` drawn by Hypothesis."""
    return bad_payload(msgtype, Drawn(draw))
