"""Large payloads written straight into shared memory (robot_relay/session.py
``SharedMemoryPool``): whole and in order through a relay, bytes again when the pool is full, and
no pool when the zenoh configuration turns shared memory off."""

from __future__ import annotations

import time
from typing import Any

import pytest
import zenoh

from robot_relay.policy import PolicyTable
from robot_relay.relay import Relay
from robot_relay.session import (
    LARGE_PAYLOAD_BYTES,
    SharedMemoryPool,
    ZenohOptions,
    close_session,
    open_session,
    shared_memory_pool,
)
from robot_relay.wire import Attachment, Catalog, RawMessage, TopicInfo, data_key

IMAGE = "sensor_msgs/msg/Image"
CAMERA = TopicInfo("/camera", IMAGE, None)


def pattern(size: int, seed: int) -> bytes:
    """``size`` bytes that differ from those of another seed at every offset."""
    return bytes((i * 7 + seed) % 251 for i in range(256)) * (size // 256) + bytes(size % 256)


def test_large_payloads_go_through_the_pool_whole_and_in_order(
    sessions: tuple[zenoh.Session, zenoh.Session], monkeypatch: pytest.MonkeyPatch,
) -> None:
    host, robot = sessions
    pooled: list[int] = []
    copy = SharedMemoryPool.copy

    def counting_copy(pool: SharedMemoryPool, payload: bytes) -> Any:
        buffer = copy(pool, payload)
        if buffer is not None:
            pooled.append(len(payload))
        return buffer

    monkeypatch.setattr(SharedMemoryPool, "copy", counting_copy)
    payloads = [pattern(1_000, 1), pattern(LARGE_PAYLOAD_BYTES - 1, 2),
                pattern(LARGE_PAYLOAD_BYTES, 3), pattern(1_000_000, 4), pattern(1_000_000, 5)]
    received: list[tuple[bytes, int]] = []
    subscriber = host.declare_subscriber(data_key("tb3", "/camera"), lambda sample: received.append(
        (sample.payload.to_bytes(),
         Attachment.unpack(sample.attachment.to_bytes(), "test").sequence
         if sample.attachment is not None else -1)))
    # Blocking: an image topic drops under congestion by default, and a loaded machine whose
    # Zenoh transmit thread waits for the CPU is congestion enough to drop the fragmented
    # payload just under the pool's size (3 of 35 runs beside two CPU burners, none of 30 blocking).
    relay = Relay(robot, Catalog("tb3", "ros2", (CAMERA,)), PolicyTable(defaults={"congestion": "block"}))
    try:
        assert relay.wait_for_host(20.0)
        for payload in payloads:
            relay.publish(RawMessage("tb3", "/camera", IMAGE, payload))
        deadline = time.monotonic() + 20
        while len(received) < len(payloads) and time.monotonic() < deadline:
            time.sleep(0.01)
    finally:
        relay.close()
        subscriber.undeclare()
    assert received == [(payload, sequence) for sequence, payload in enumerate(payloads)]
    assert pooled == [LARGE_PAYLOAD_BYTES, 1_000_000, 1_000_000]
    assert relay.published_bytes == sum(map(len, payloads))


def test_a_full_pool_gives_none_until_its_buffers_are_released() -> None:
    pool = SharedMemoryPool(256 * 1024)
    payload = pattern(100_000, 6)
    held = [pool.copy(payload), pool.copy(payload)]
    assert [bytes(buffer) if buffer is not None else None for buffer in held] == [payload] * 2
    assert pool.copy(payload) is None  # a third does not fit: the relay puts the bytes instead
    del held
    again = pool.copy(payload)
    assert again is not None
    assert bytes(again) == payload
    assert pool.copy(pattern(LARGE_PAYLOAD_BYTES - 1, 7)) is None  # small: never pooled


@pytest.mark.parametrize(("cfg", "pooled"), [
    ((), True),
    (("transport/shared_memory/enabled:false",), False),
    (("transport/shared_memory/transport_optimization/enabled:false",), False),
])
def test_a_session_has_a_pool_while_zenoh_shared_memory_is_on(
    cfg: tuple[str, ...], pooled: bool,
) -> None:
    session = open_session(ZenohOptions(multicast_scouting=False, cfg=cfg))
    try:
        assert (shared_memory_pool(session) is not None) == pooled
    finally:
        close_session(session)
    assert shared_memory_pool(session) is None
