"""Live input: every robot this host reaches over Zenoh, swanky relays (zenoh.py) and, unless
``--no-rmw-zenoh``, rmw_zenoh robots (rmw_zenoh.py), through one set of per-robot queues
(queues.py), so a robot reached both ways is still converted on one thread."""

from __future__ import annotations

import logging

import zenoh

from host_bridge.core.shards import Shard
from host_bridge.errors import relay_errors
from host_bridge.inputs.base import Deliver, gathered
from host_bridge.inputs.queues import RobotQueues
from host_bridge.inputs.rmw_zenoh import RmwZenohInput
from host_bridge.inputs.zenoh import ZenohInput
from robot_relay.session import ZenohOptions, open_session

log = logging.getLogger("swanky.host")


def open_host_session(options: ZenohOptions) -> zenoh.Session:
    """The host's Zenoh session (live robots, ``--list``); a bad flag or config file is a host
    ConfigError with the session's own words."""
    with relay_errors():
        return open_session(options)


class LiveInput:
    """The :class:`~host_bridge.inputs.base.Input` of live robots on ``session`` (the caller's:
    the stats and the robots' file service use it too)."""

    def __init__(
        self,
        session: zenoh.Session,
        *,
        robots: str = "*",
        domain: int = 0,
        root_robot: str = "robot",
        rmw_zenoh: bool = True,
        shard: Shard | None = None,
    ) -> None:
        self.queues = RobotQueues()
        self._relays = ZenohInput(session, robots=robots, queues=self.queues, shard=shard)
        self.clocks = self._relays.clocks
        """The relays' clocks against the PC's (rmw_zenoh robots have no relay to ask: their
        receive times are the host's own)."""
        self._receivers: list[ZenohInput | RmwZenohInput] = [self._relays]
        # rmw_zenoh robots announce no relay to spread by: the first worker reads them all.
        if rmw_zenoh and (shard is None or shard.index == 0):
            self._receivers.append(RmwZenohInput(session, domain, robots, root_robot, self.queues))
        self._closed = False

    @property
    def last_activity(self) -> float:
        return self.queues.last_activity

    def start(self, deliver: Deliver) -> None:
        self.queues.serve(lambda items: deliver(gathered(items)))

    def ended(self) -> bool:
        if self.queues.error is not None:
            raise self.queues.error
        return False

    def close(self) -> None:
        """Stop receiving, then let each robot's worker convert what is queued."""
        if self._closed:
            return
        self._closed = True
        for receiver in self._receivers:
            receiver.close()
        self.queues.close()
        if self.queues.dropped:
            log.warning("messages dropped because the host fell behind:\n%s", self.queues.drop_summary())
        if self._relays.refused:
            log.warning("messages refused because they claimed another type than their relay's "
                        "catalog announces for their topic:\n%s", "\n".join(
                            f"[{robot}] {topic}: {count}"
                            for (robot, topic), count in sorted(self._relays.refused.items())))

