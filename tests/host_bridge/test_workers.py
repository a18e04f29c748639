"""``swanky-host --workers N`` without processes: which worker converts which robot, what each
worker is told (host_bridge/workers.py), and the flags it refuses. The processes themselves run
in tests/integration/test_demo.py."""

from __future__ import annotations

from pathlib import Path

import pytest

from host_bridge import cli
from host_bridge.app import HostOptions
from host_bridge.core.destinations import SinkOptions
from host_bridge.core.shards import Shard
from host_bridge.workers import shard_path, worker_options
from robot_relay.session import ZenohOptions

DEMO_FLEET = ["sim", *(f"sim{i}" for i in range(2, 26))]


pytestmark = pytest.mark.usefixtures("keep_signal_handlers")  # main() installs its own


@pytest.mark.parametrize("count", [1, 2, 3, 4])
def test_every_robot_belongs_to_exactly_one_worker(count: int) -> None:
    shards = [Shard(index, count) for index in range(count)]
    for robot in [*DEMO_FLEET, "tb3_0", "east-1", "west-12", "robot"]:
        assert sum(shard.owns(robot) for shard in shards) == 1, robot


def test_the_demo_fleet_is_spread_evenly_over_two_workers() -> None:
    assert [sum(Shard(index, 2).owns(robot) for robot in DEMO_FLEET) for index in (0, 1)] == [13, 12]


def test_a_worker_gets_the_router_one_viewer_one_recording_and_files_of_its_own() -> None:
    options = HostOptions(
        sink=SinkOptions(spawn=True, save=Path("/data/fleet.rrd")),
        zenoh=ZenohOptions(listen=("tcp/0.0.0.0:7447",)),
        demo=True, robots="25", record_mcap=Path("/data/fleet.mcap"), workers=2, duration=30.0,
    )
    shard = Shard(1, 2)
    worker = worker_options(options, shard, endpoint="tcp/127.0.0.1:40000", robots="sim$*",
                            viewer="rerun+http://127.0.0.1:9876/proxy", recording_id="fleet-id")
    assert (worker.workers, worker.shard, worker.demo, worker.robots) == (1, shard, False, "sim$*")
    assert worker.zenoh == ZenohOptions(mode="client", connect=("tcp/127.0.0.1:40000",),
                                        multicast_scouting=False)
    assert worker.sink == SinkOptions(connect="rerun+http://127.0.0.1:9876/proxy",
                                      save=Path("/data/fleet-worker1.rrd"), recording_id="fleet-id")
    assert worker.record_mcap == Path("/data/fleet-worker1.mcap")
    assert worker.host_name == "worker1"
    assert worker.duration == 30.0
    named = worker_options(HostOptions(host_name="east", workers=2), Shard(0, 2), endpoint="e",
                           robots="*", viewer=None, recording_id="r")
    assert named.host_name == "east-worker0"
    assert shard_path(None, shard) is None


def test_workers_reach_the_options() -> None:
    assert cli.host_options(cli.parse_args(["--demo", "--workers", "2"])).workers == 2
    assert cli.host_options(cli.parse_args([])).workers == 1


@pytest.mark.parametrize("value", ["0", "65", "two"])
def test_a_worker_count_out_of_range_is_named(capsys: pytest.CaptureFixture[str], value: str) -> None:
    with pytest.raises(SystemExit) as exited:
        cli.main(["--workers", value, "--save", "out.rrd"])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"swanky-host: error: argument --workers: {value!r} is not a number of worker processes: "
        "1 to 64")


@pytest.mark.parametrize(("flags", "named"), [
    (["--bag", "BAG"], "--workers: a bag is converted by one process"),
    (["--serve-web"], "--workers: --serve-web serves the recording from the host's own process"),
])
def test_workers_with_what_one_process_must_do_is_refused_before_anything_opens(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, flags: list[str], named: str,
) -> None:
    bag = tmp_path / "robot.mcap"
    bag.write_bytes(b"")
    argv = [str(bag) if flag == "BAG" else flag for flag in flags]
    assert cli.main(["--workers", "2", *argv]) == 2
    err = capsys.readouterr().err
    assert f"swanky-host: error: {named}" in err
    assert "Rerun web viewer" not in err
