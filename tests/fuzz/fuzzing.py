"""What the fuzz tests share: reproducible, bounded Hypothesis settings and the ways a message
goes bad on the way (cut short, grown, bytes flipped, a length prefix made huge).

``derandomize`` and no example database make every run try the same inputs, so CI fails the same
way on every machine; the example counts keep the whole fuzz set well under a minute on a loaded
2-core machine, and the deadline is generous for the same reason (a slow example is not a bug).
"""

from __future__ import annotations

import datetime

from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

FUZZ = settings(
    derandomize=True,
    database=None,
    max_examples=300,
    deadline=datetime.timedelta(seconds=5),
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

# Values a u32 length prefix is set to: each claims more than any payload holds.
HUGE_U32 = (0x7FFFFFFF, 0xFFFFFFFF, 0x10000000, 1_000_000_000)


@st.composite
def mutated(draw: st.DrawFn, data: bytes) -> bytes:
    """``data`` gone bad in one of the ways a link, a disk or an attacker makes it."""
    size = len(data)
    kind = draw(st.sampled_from(["truncate", "extend", "flip", "huge_u32", "random"]))
    if kind == "truncate":
        # Each length class: empty, inside the 4-byte CDR header, just after it, the middle,
        # one byte short.
        cut = draw(st.sampled_from(sorted({0, 1, 3, 4, 5, 8, size // 2, max(size - 1, 0)})))
        return data[:cut]
    if kind == "extend":
        return data + draw(st.binary(min_size=1, max_size=64))
    if kind == "flip" and size:
        out = bytearray(data)
        for _ in range(draw(st.integers(1, 8))):
            out[draw(st.integers(0, size - 1))] ^= draw(st.integers(1, 255))
        return bytes(out)
    if kind == "huge_u32" and size >= 8:
        # A CDR sequence/string length (u32, 4-aligned after the 4-byte header) made huge.
        at = 4 + 4 * draw(st.integers(0, (size - 8) // 4))
        out = bytearray(data)
        out[at:at + 4] = draw(st.sampled_from(HUGE_U32)).to_bytes(4, "little")
        return bytes(out)
    return draw(st.binary(max_size=max(size, 16)))
