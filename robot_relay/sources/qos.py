"""The QoS a relay subscribes with, adapted to a topic's publishers like ``ros2 bag record``."""

from __future__ import annotations

from collections.abc import Sequence

from robot_relay.wire import QosProfile

# (reliability, durability, depth) of one publisher, policies spelt as rclpy's enum names in
# lower case: "reliable" / "best_effort" / ..., "transient_local" / "volatile" / ...
Offer = tuple[str, str, int]


def adapted_qos(offers: Sequence[Offer]) -> QosProfile:
    """Request what every publisher can serve, as rosbag2_transport's
    ``Rosbag2QoS::adapt_request_to_offers`` does: reliable only when all publishers are reliable
    (a reliable request does not match a best-effort publisher), transient-local only when all
    are (a transient-local request does not match a volatile one).

    Depth differs on purpose: rosbag2 keeps its default of 10, but a latched topic's cache must
    hold every publisher's latched history (several /tf_static broadcasters keep one message
    each), so transient-local topics get the sum of the publishers' depths; others the deepest.
    """
    if not offers:
        return QosProfile()
    reliable = all(reliability == "reliable" for reliability, _, _ in offers)
    latched = all(durability == "transient_local" for _, durability, _ in offers)
    depths = [max(depth, 1) for _, _, depth in offers]
    return QosProfile(
        reliability="reliable" if reliable else "best_effort",
        durability="transient_local" if latched else "volatile",
        depth=sum(depths) if latched else max(depths),
    )
