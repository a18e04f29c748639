"""A process's heap (the live relay's, swanky-host --bag's): freed message buffers kept for the next one.

A large message (an image, a cloud: about 1 MB) passes through fresh buffers of its size: the
serialized message rclpy takes it into, the Python bytes made of it. glibc serves such a buffer
with its own mmap (or trims the heap top when it is freed), so every message faults its pages
in again and the kernel clears and unmaps them: 15-20 % of the live relay's CPU for large
messages (perf: clear_page_erms, exc_page_fault, unmap_page_range). Telling glibc to serve
buffers up to :data:`LARGEST_REUSED` from the heap and to keep up to :data:`KEPT_FREE` of freed
heap makes the next message reuse the same pages: benchmarks/relay_cpu.py's large messages cost
the relay 1.3-1.65 ms of CPU each instead of 2.95-2.99 (two runs each, alternated), for 3 MB
more resident memory.
"""

from __future__ import annotations

import ctypes
import logging

log = logging.getLogger("swanky.relay")

M_TRIM_THRESHOLD = -1  # <malloc.h>
M_MMAP_THRESHOLD = -3
LARGEST_REUSED = 32 * 1024 * 1024
"""glibc's upper bound for M_MMAP_THRESHOLD on 64-bit systems (a larger value is refused)."""
KEPT_FREE = 64 * 1024 * 1024


def keep_freed_buffers() -> bool:
    """Set glibc's thresholds for this process; False where the C library has no ``mallopt``
    (musl) or refuses them (32-bit systems allow smaller thresholds), which changes nothing."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    kept = bool(mallopt(M_MMAP_THRESHOLD, LARGEST_REUSED)) and bool(
        mallopt(M_TRIM_THRESHOLD, KEPT_FREE)
    )
    if not kept:
        log.debug("glibc's heap thresholds not set: large messages use fresh pages each")
    return kept
