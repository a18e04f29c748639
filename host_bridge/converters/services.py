"""Service events (``/<service>/_service_event``, ``<pkg>/srv/<Name>_Event``) as a text log.

From Iron on, a service with introspection enabled publishes one event per request sent,
request received, response sent and response received, and ``ros2 bag record --services``
records them. Each becomes one line on the topic's entity (``/<robot>/<service>/_service_event``
by default), stamped with the event's own time, e.g.::

    request received #7 (client 0102030405060708090a0b0c0d0e0f10): {a: 2, b: 3}

The payload is written the way ``ros2 topic echo --flow-style`` writes a message. Services whose
introspection is set to ``metadata`` record no payload; their lines say so.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from host_bridge.converters.generic import data_fields
from host_bridge.converters.logs import _INFO, text_converter

# service_msgs/ServiceEventInfo event_type: REQUEST_SENT, REQUEST_RECEIVED, RESPONSE_SENT,
# RESPONSE_RECEIVED.
EVENT_NAMES = ("request sent", "request received", "response sent", "response received")
# Array elements written out before the rest is summarised, as `ros2 topic echo` truncates.
MAX_ELEMENTS = 16


def value_text(value: Any) -> str:
    """One field value in YAML flow style: ``{x: 1.0, y: 2.0}``, ``[1, 2]``, ``'text'``."""
    if hasattr(value, "__dataclass_fields__"):
        return message_text(value)
    if isinstance(value, np.ndarray):
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        shown = [value_text(v) for v in value[:MAX_ELEMENTS]]
        if len(value) > MAX_ELEMENTS:
            shown.append(f"... ({len(value)} elements)")
        return f"[{', '.join(shown)}]"
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, str):
        return "'" + value.replace("'", "''") + "'"
    return str(value)


def message_text(msg: Any) -> str:
    return "{" + ", ".join(f"{f.name}: {value_text(getattr(msg, f.name))}" for f in data_fields(msg)) + "}"


def event_text(event: Any) -> str:
    info = event.info
    kind = int(info.event_type)
    name = EVENT_NAMES[kind] if kind < len(EVENT_NAMES) else f"event type {kind}"
    payloads = event.request if kind < 2 else event.response
    payload = (
        message_text(payloads[0]) if len(payloads)
        else "(no payload recorded: the service's introspection is set to metadata)"
    )
    client = bytes(np.asarray(info.client_gid, dtype=np.uint8)).hex()
    return f"{name} #{int(info.sequence_number)} (client {client}): {payload}"


# logs.py's text converter (a TextLog column per run, with the message's own stamp), reused.
SPEC = text_converter(event_text, lambda msgs: [_INFO] * len(msgs), stamp=lambda m: m.info.stamp)
