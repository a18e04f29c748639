"""The QoS a relay subscribes with, adapted to a topic's publishers like ``ros2 bag record``."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

from robot_relay.wire import QosProfile

# (reliability, durability, depth) of one publisher, policies spelt as rclpy's enum names in
# lower case: "reliable" / "best_effort" / ..., "transient_local" / "volatile" / ...
Offer = tuple[str, str, int]

# The live relay's queues hold at least this many messages (rosbag2 subscribes with depth 10,
# rmw_qos_profile_default). Fast DDS reports depth 0 for every publisher: without a floor the
# queue would hold one message, and any stall of the relay longer than one message period would
# overwrite reliable messages before they are forwarded.
LIVE_DEPTH_FLOOR = 10
# A volatile stream's queue is what rides out the relay's own stalls (garbage collection, a
# loaded CPU, a congested link blocking a reliable topic's Zenoh put) and its latency budget
# (robot_relay.sources.take_loop: the take loop turns at most every 0.1 s by default): 10 holds
# a third of a second of 30 Hz odometry, which a loaded machine exceeds; 100 hold 3.3 s of it and
# the 0.1 s of a 1 kHz IMU. The memory is used only while the relay lags behind.
LIVE_STREAM_FLOOR = 100


def adapted_qos(offers: Sequence[Offer], floor: int = 1) -> QosProfile:
    """Request what every publisher can serve, as rosbag2_transport's
    ``Rosbag2QoS::adapt_request_to_offers`` does: reliable only when all publishers are reliable
    (a reliable request does not match a best-effort publisher), transient-local only when all
    are (a transient-local request does not match a volatile one).

    Depth (the queue of messages received and not yet forwarded, and a latched topic's cache for
    late hosts): the deepest publisher's, and for transient-local topics the sum of the
    publishers' depths, since a new subscription receives every publisher's latched history at
    once (several /tf_static broadcasters); a publisher reporting 0 counts as 1. Never below
    ``floor``: :data:`LIVE_DEPTH_FLOOR` live, 1 for a bag's recorded offers.
    """
    if not offers:
        return QosProfile()
    reliable = all(reliability == "reliable" for reliability, _, _ in offers)
    latched = all(durability == "transient_local" for _, durability, _ in offers)
    depths = [max(depth, 1) for _, _, depth in offers]
    return QosProfile(
        reliability="reliable" if reliable else "best_effort",
        durability="transient_local" if latched else "volatile",
        depth=max(floor, sum(depths) if latched else max(depths)),
    )


def live_qos(offers: Sequence[Offer]) -> QosProfile:
    """What the live relay subscribes with: :func:`adapted_qos` with :data:`LIVE_DEPTH_FLOOR`,
    volatile streams (reliable or best effort) at least :data:`LIVE_STREAM_FLOOR` deep. Latched
    topics keep the smaller floor: their depth also sizes the cache late hosts get."""
    qos = adapted_qos(offers, LIVE_DEPTH_FLOOR)
    if qos.durability == "volatile":
        return replace(qos, depth=max(qos.depth, LIVE_STREAM_FLOOR))
    return qos
