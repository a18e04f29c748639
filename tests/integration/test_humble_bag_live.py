"""A Humble sqlite3 bag (no message definitions) replayed by swanky-relay and seen live by
swanky-host: the same topics convert, and the same one is named and skipped, as offline."""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from host_bridge.core.contract import WARNINGS_PATH
from host_bridge.inputs.zenoh import CATALOG_TIMEOUT_S
from tests.host_bridge.test_user_bags import convert, humble_bag, texts
from tests.integration.procs import command, free_port, running
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration


def test_relay_replays_a_humble_bag_as_the_host_converts_it(tmp_path: Path) -> None:
    bag = humble_bag(tmp_path / "humble")
    port = free_port()
    live = tmp_path / "live.rrd"
    host = command("host_bridge.cli", "-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting",
                   "--no-rmw-zenoh", "--save", str(live), "--until-idle", "8", "--duration", "60")
    relay = command("robot_relay.cli", "--robot", "robot", "--bag", str(bag), "-e",
                    f"tcp/127.0.0.1:{port}", "--no-multicast-scouting", "--wait-for-host", "60")
    # The relay first: it retries (zenoh: at most 4 s apart) until the host listens, so the
    # host's idle clock (8 s) starts when the relay is about to connect.
    with running(relay) as relay_proc:
        time.sleep(1.0)
        with running(host) as host_proc:
            assert relay_proc.wait(timeout=90) == 0, relay_proc.stderr.read() if relay_proc.stderr else ""
            assert host_proc.wait(timeout=60) == 0
    rows = entity_rows(live)
    offline = convert(bag, tmp_path / "offline.rrd")

    assert texts(rows["/robot/chatter"]) == texts(offline["/robot/chatter"]) == [
        "hello 0", "hello 1", "hello 2",
    ]
    grids = [[r["GridMap:data"][0] for r in rs if r.get("GridMap:data")]
             for rs in (rows["/robot/global_costmap/costmap_raw"],
                        offline["/robot/global_costmap/costmap_raw"])]
    assert grids[0] == grids[1] == [[100, 255, 1, 0, 50, 99]]
    # Besides the type named: a relay whose catalog came late (the query unanswered, 1 full
    # suite run in 3 on the 2-core machine, 2026-11-29) is said too, and its topics decode with
    # the bundled Humble types all the same (the rows above).
    late = f"robot robot did not answer its catalog (swanky/robot/catalog) within {CATALOG_TIMEOUT_S} s"
    warnings = [text for text in texts(rows[WARNINGS_PATH]) if late not in text]
    assert len(warnings) == 1, warnings
    [warning] = warnings
    assert warning.startswith("[robot] /sensor/reading: type my_msgs/msg/Reading has no definition")
    assert texts(offline[WARNINGS_PATH]) == [warning]
