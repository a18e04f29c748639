"""diagnostic_msgs/DiagnosticArray: one text log per status, plus a plot per numeric value.

Status names are free text ("battery: Motor 1/2", aggregator paths like "/Robot/Lidar"), so
each becomes ONE escaped entity path part: a slash in a name must not invent hierarchy.

Levels: OK -> INFO, WARN -> WARN, ERROR -> ERROR. STALE (no update from the source for a
while) maps to WARN with the text prefixed "stale: ": it needs attention like a warning, and a
DEBUG line would hide a sensor that went silent. Unknown levels are treated the same way.
"""

from __future__ import annotations

from typing import Any

import rerun as rr

from host_bridge.core.contract import ConvertContext, LogEntry, LogItem, per_message

_OK, _WARN, _ERROR = 0, 1, 2
_LEVELS = {
    _OK: str(rr.TextLogLevel.INFO),
    _WARN: str(rr.TextLogLevel.WARN),
    _ERROR: str(rr.TextLogLevel.ERROR),
}
_UNNAMED = "unnamed"


def _float_or_none(text: str) -> float | None:
    try:
        return float(text)
    except ValueError:
        return None


def status_text(status: Any) -> str:
    """'message | key=value, ...'; 'stale: ' in front when the level is not OK/WARN/ERROR."""
    pairs = ", ".join(f"{kv.key}={kv.value}" for kv in status.values)
    text = f"{status.message} | {pairs}" if pairs else str(status.message)
    return text if int(status.level) in _LEVELS else f"stale: {text}"


def _diagnostic_array(msg: Any, ctx: ConvertContext) -> list[LogEntry]:
    entries: list[LogEntry] = []
    for status in msg.status:
        path = ctx.child_path(rr.escape_entity_path_part(status.name.strip() or _UNNAMED))
        level = _LEVELS.get(int(status.level), _LEVELS[_WARN])
        entries.append(LogItem(path, (rr.TextLog(status_text(status), level=level),)))
        for kv in status.values:
            value = _float_or_none(kv.value)
            if value is not None and kv.key.strip():
                key = rr.escape_entity_path_part(kv.key.strip())
                entries.append(LogItem(f"{path}/{key}", (rr.Scalars(value),)))
    return entries


SPEC = per_message(_diagnostic_array)
