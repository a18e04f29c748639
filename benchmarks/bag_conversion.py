"""Offline bag -> .rrd speed against Rerun's own Rust MCAP importer, measured side by side.

Baseline: `rerun mcap convert BAG -o out.rrd` (Rust, same machine, same run).
Ours: `swanky-host --bag BAG --save out.rrd`, run in-process so interpreter start-up is excluded.
Prints messages/s for both and the ratio ours/baseline (wall time); lower is better.

    .venv/bin/python benchmarks/bag_conversion.py [BAG]   # default: nav2_turtlebot.mcap
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from host_bridge.cli import main as host_main

DEFAULT_BAG = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "tf_nav2_sim_evo" / "nav2_turtlebot.mcap"
)


def best_of(runs: int, action: object) -> float:
    timings = []
    for _ in range(runs):
        started = time.perf_counter()
        action()  # type: ignore[operator]
        timings.append(time.perf_counter() - started)
    return min(timings)


def main() -> int:
    bag = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_BAG
    rerun = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    if not bag.exists() or rerun is None:
        print(f"needs {bag} and the rerun CLI", file=sys.stderr)
        return 1
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as reader:
        count = reader.message_count
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        baseline = best_of(3, lambda: subprocess.run(
            [rerun, "mcap", "convert", str(bag), "-o", str(out / "rust.rrd")],
            check=True, capture_output=True,
        ))
        ours = best_of(3, lambda: host_main(["--bag", str(bag), "--save", str(out / "ours.rrd")]))
    print(f"bag: {bag.name}, {count} messages")
    print(f"baseline rerun mcap convert: {baseline:.3f} s ({count / baseline:,.0f} msg/s)")
    print(f"swanky-host --bag:           {ours:.3f} s ({count / ours:,.0f} msg/s)")
    print(f"ratio ours/baseline: {ours / baseline:.1f}x")
    return 0


if __name__ == "__main__":
    sys.exit(main())
