"""The reliability table, docs/RELIABILITY.md, written by the test run itself.

A test that tries something hostile (a bad link, a crash, malformed input, a client without a
certificate) records what it tried, how many times, what survived and what was lost, with the
``reliability`` fixture (tests/conftest.py)::

    def test_link_cut(reliability: Record) -> None:
        ...
        reliability("Bad links", "link cut for 30 s, then restored", tried="1 cut",
                    survived="all 412 reliable /odom messages, in order", lost="0")

At the end of the session the rows recorded replace every row of the tests that recorded them
(so a row whose wording changed leaves no stale copy); the others stay, so a run of one test
file updates its rows only. Each row says when it
was measured. A test that fails records nothing: its row keeps the last value that passed,
and the date shows how old that is.
"""

from __future__ import annotations

import datetime
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

TABLE = Path(__file__).resolve().parents[1] / "docs" / "RELIABILITY.md"
COLUMNS = ("area", "what was tried", "how many times", "what survived", "what was lost", "test",
           "measured")
INTRO = """# Reliability: what was tried, what survived, what was lost

Written by the test run (`tests/reliability.py`): each row is replaced by the test that
produces it whenever it passes, so every figure here comes from a run of the README test
command (or of that one test), on the date shown. Edit the tests, not this table.
"""


@dataclass(frozen=True, slots=True)
class Trial:
    area: str
    what: str
    tried: str
    survived: str
    lost: str
    test: str
    measured: str

    def cells(self) -> tuple[str, ...]:
        return (self.area, self.what, self.tried, self.survived, self.lost, self.test, self.measured)


Record = Callable[..., None]
recorded: list[Trial] = []


def recorder(test: str) -> Record:
    """The ``reliability`` fixture's function for the test named ``test`` (its node id)."""

    def record(area: str, what: str, *, tried: str, survived: str, lost: str) -> None:
        today = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d")
        recorded.append(Trial(area, what, tried, survived, lost, test, today))

    return record


def _cell(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _read(path: Path) -> list[Trial]:
    if not path.exists():
        return []
    rows = []
    for line in path.read_text().splitlines():
        if not line.startswith("| ") or line.startswith(("| area ", "|---")):
            continue
        cells = [c.strip().replace("\\|", "|") for c in re.split(r"(?<!\\)\|", line)[1:-1]]
        if len(cells) == len(COLUMNS):
            rows.append(Trial(*cells))
    return rows


def write_table(trials: list[Trial], path: Path = TABLE) -> None:
    """Merge ``trials`` into the table at ``path``: the rows of the tests that made them go."""
    tests = {t.test for t in trials}
    rows = {(t.area, t.what): t for t in _read(path) if t.test not in tests}
    rows.update({(t.area, t.what): t for t in trials})
    lines = [INTRO, "| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for trial in sorted(rows.values(), key=lambda t: (t.area, t.what)):
        lines.append("| " + " | ".join(_cell(c) for c in trial.cells()) + " |")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n".join(lines) + "\n")
