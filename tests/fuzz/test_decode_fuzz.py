"""Every registered type through the real Dispatcher with fuzzed CDR (issue 14): messages whose
fields hold NaN, infinities, extreme integers (declared sizes of 10^9) and odd strings, and
serialized messages cut short, grown, flipped or given huge length prefixes. Nothing escapes the
dispatcher, each bad message is counted (converted or dropped, never lost from the counts), each
(topic, error kind) is warned about once, and the good topic in the same batches converts every
value."""

from __future__ import annotations

import re
import resource
from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any, cast

import pytest
from hypothesis import given, settings

from host_bridge.core.contract import WARNINGS_PATH, ColumnsItem, LogEntry, LogItem
from host_bridge.core.decode import Decoder
from host_bridge.pipeline.dispatch import Dispatcher
from host_bridge.table.config import HostConfig
from host_bridge.table.registry import Row, default_registry
from robot_relay.wire import RawMessage
from tests.fuzz.fuzzing import FUZZ, STORE, payloads
from tests.reliability import Record

# NaN and infinities in the input make numpy say so; that is the point, not a problem.
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

REGISTRY = default_registry()
DECODER = Decoder(STORE)
CONFIG = HostConfig.builtin(REGISTRY)
# Rows of types a ROS 2 host can meet with the bundled definitions (rosgraph_msgs/Log is ROS 1's).
ROWS = [row for row in REGISTRY.rows() if not row.is_family and row.msgtype in STORE.fielddefs]
EXAMPLES_PER_TYPE = 30
GOOD_TOPIC = "/good"
FLOAT64 = "std_msgs/msg/Float64"


class RecordingSink:
    """The Sink the dispatcher logs to, keeping every entry."""

    def __init__(self) -> None:
        self.entries: list[LogEntry] = []

    def log(self, entries: Sequence[LogEntry], times: Mapping[str, int]) -> None:
        self.entries.extend(entries)

    def close(self) -> None:
        pass

    def scalars(self, path: str) -> list[float]:
        """The values logged at ``path``, rows (one message) and columns (a run) alike."""
        values: list[float] = []
        for item in self.entries:
            if item.path != path:
                continue
            if isinstance(item, ColumnsItem):
                for column in item.columns:
                    if column.component_descriptor().component == "Scalars:scalars":
                        values.extend(v for row in column.as_arrow_array().to_pylist() for v in row)
                continue
            for archetype in item.archetypes:
                values.extend(cast(Any, archetype).scalars.as_arrow_array().to_pylist())
        return values

    def warnings(self) -> list[str]:
        return [
            text
            for item in self.entries if isinstance(item, LogItem) and item.path == WARNINGS_PATH
            for archetype in item.archetypes
            for text in cast(Any, archetype).text.as_arrow_array().to_pylist()
        ]


def _float64(value: float) -> bytes:
    return bytes(STORE.serialize_cdr(STORE.types[FLOAT64](data=value), FLOAT64))


def _fuzz_row(row: Row) -> Counter[str]:
    """Batches of [bad, good, bad] through one Dispatcher; returns what became of the bad ones."""
    topic = "/robot_description" if row.topics is not None else "/fuzzed"
    sink = RecordingSink()
    dispatcher = Dispatcher(sink, registry=REGISTRY, decoder=DECODER, config=CONFIG)
    seen: Counter[str] = Counter()
    sent = 0

    @settings(FUZZ, max_examples=EXAMPLES_PER_TYPE)
    @given(payloads(row.msgtype), payloads(row.msgtype))
    def run(first: tuple[bytes, str], second: tuple[bytes, str]) -> None:
        nonlocal sent
        counters = dispatcher.counters.get(("tb3", topic))
        before = (0, 0, 0) if counters is None else (
            counters.received, counters.converted, counters.dropped)
        dispatcher.dispatch([
            RawMessage("tb3", topic, row.msgtype, first[0], log_ns=2 * sent + 1),
            RawMessage("tb3", GOOD_TOPIC, FLOAT64, _float64(sent), log_ns=2 * sent + 1),
            RawMessage("tb3", topic, row.msgtype, second[0], log_ns=2 * sent + 2),
        ])
        sent += 1
        counters = dispatcher.counters[("tb3", topic)]
        received, converted, dropped = (
            counters.received - before[0], counters.converted - before[1],
            counters.dropped - before[2],
        )
        assert received == 2
        assert converted + dropped == 2
        seen["converted"] += converted
        seen["dropped"] += dropped
        seen[first[1]] += 1
        seen[second[1]] += 1

    run()
    dispatcher.close()
    assert sink.scalars(f"/tb3{GOOD_TOPIC}") == [float(i) for i in range(sent)]
    good = dispatcher.counters[("tb3", GOOD_TOPIC)]
    assert (good.received, good.converted, good.dropped, good.warnings) == (sent, sent, 0, 0)
    counters = dispatcher.counters[("tb3", topic)]
    assert counters.dropped == seen["dropped"]
    # One warning per (topic, kind); the rest are counted.
    warned = [re.search(r"\(further (\w+)s on this topic", text) for text in sink.warnings()]
    kinds = [m.group(1) for m in warned if m is not None]
    assert len(kinds) == len(warned) == len(set(kinds))
    assert counters.warnings >= len(kinds)
    if seen["dropped"]:
        assert kinds
    seen["warnings"] += len(kinds)
    return seen


def test_every_registered_type_survives_fuzzed_cdr(reliability: Record) -> None:
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    totals: Counter[str] = Counter()
    failures: dict[str, str] = {}
    for row in ROWS:
        try:
            totals += _fuzz_row(row)
        except AssertionError as err:  # also Hypothesis' report of a failing example
            failures[row.msgtype] = str(err)[:3000]
    assert failures == {}
    grown_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before) / 1024
    assert grown_mb < 250
    bad = 2 * EXAMPLES_PER_TYPE * len(ROWS)
    assert totals["converted"] + totals["dropped"] == bad
    reliability(
        "Hostile input",
        f"fuzzed CDR of every registered type ({len(ROWS)} table rows) through the dispatcher (fields NaN, "
        "±inf, extreme integers and 10^9 sizes; bytes cut, grown, flipped, huge length "
        "prefixes), each batch beside a good topic",
        tried=f"{bad} bad messages ({totals['odd fields']} with odd fields, "
              f"{totals['mutated bytes']} with mutated bytes)",
        survived=f"host (memory +{grown_mb:.0f} MB), every one counted: {totals['converted']} "
                 f"converted, {totals['dropped']} dropped with {totals['warnings']} warnings "
                 f"(one per topic and kind); all {bad // 2} good messages beside them converted",
        lost=f"the {totals['dropped']} bad messages only",
    )
