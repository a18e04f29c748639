"""The table writer of docs/RELIABILITY.md: rows merge by (area, what), cells keep their pipes."""

from __future__ import annotations

from pathlib import Path

from tests.reliability import Trial, _read, write_table


def test_a_tests_rows_are_replaced_and_keep_escaped_pipes(tmp_path: Path) -> None:
    table = tmp_path / "RELIABILITY.md"
    old = Trial("Bad links", "link cut", "1", "all", "0", "t::a", "2026-11-01")
    other = Trial("Security", "no certificate", "3 | 4", "none", "0", "t::b", "2026-11-01")
    write_table([old, other], table)
    worded_before = Trial("Bad links", "link cut (old wording)", "1", "all", "0", "t::a", "2026-11-01")
    write_table([worded_before], table)
    new = Trial("Bad links", "link cut", "2", "all 10", "1 scan", "t::a", "2026-11-23")
    write_table([new], table)
    assert _read(table) == [new, other]
    assert "3 \\| 4" in table.read_text()
