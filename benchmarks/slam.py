"""Host-side SLAM's cost: CPU per scan, real-time factor and peak memory, against the
odometry-only map (the same scans drawn into the same grid where odometry puts them: what a
host without SLAM would draw, and its cost is the floor), for a TurtleBot's laser (360 beams,
10 Hz, 3.5 m) and a Hokuyo UTM-30LX (1080 beams over 270 deg, 40 Hz, 30 m).

The logs are the demo apartment's loop with 5 % odometry scale error, 2 deg/m heading drift and
1 cm of range noise (``tests/host_bridge/slam/robot_logs.py``), made before the clock starts.
Each case runs in a process of its own so its peak RSS is its own; CPU is ``time.process_time``
(all threads) around the engine alone. Target (issue 21): one host core keeps up 10x faster
than real time with the first laser. The trajectory's RMS error against the truth is printed
beside, so a faster engine cannot hide a worse map. Run: ``.venv/bin/python benchmarks/slam.py``.
"""

from __future__ import annotations

import argparse
import json
import math
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BUDGET_SECONDS = 240
TARGET_REAL_TIME = 10.0
LASERS = {
    "360x10Hz": {"seconds": 60.0, "scan_hz": 10.0, "beams": 360, "range_max": 3.5},
    "1080x40Hz": {"seconds": 30.0, "scan_hz": 40.0, "beams": 1080, "fov_deg": 270.0, "range_max": 30.0},
}


def run_case(laser: str, mode: str) -> dict[str, float]:
    from host_bridge.slam.engine import Slam
    from host_bridge.slam.grid import TiledGrid
    from host_bridge.slam.pose import pose2, to_matrix
    from host_bridge.slam.scan import scan_from_ranges
    from host_bridge.slam.settings import SlamSettings
    from tests.host_bridge.slam.robot_logs import LASER_XY, LaserLog, simulate

    log = LaserLog(range_noise=0.01, **LASERS[laser])  # type: ignore[arg-type]
    run = simulate(log)
    mount = to_matrix(pose2(*LASER_XY, 0.0))
    scans = [scan_from_ranges(s.ranges, run.angle_min, run.angle_increment, log.range_min,
                              log.range_max).moved(mount) for s in run.scans if s.ranges is not None]
    settings = SlamSettings(enabled=True)
    slam = Slam(settings) if mode == "slam" else None
    grid = TiledGrid(settings.resolution)
    per_scan = []
    started = time.process_time()
    for sample, scan in zip(run.scans, scans, strict=True):
        before = time.process_time()
        if slam is not None:
            slam.add(scan, sample.stamp_ns, sample.odom)
        else:
            grid.add(scan, sample.odom)
        per_scan.append(time.process_time() - before)
    cpu = time.process_time() - started
    if slam is not None:
        slam.occupancy()
        poses = slam.trajectory()[1]
    else:
        grid.dense()
        poses = np.array([s.odom for s in run.scans])
    truth = np.array([s.truth for s in run.scans])
    rms = math.sqrt(float(np.mean(np.sum((poses[:, :2] - truth[:, :2]) ** 2, axis=1))))
    return {
        "scans": len(scans), "data_s": log.seconds, "cpu_s": cpu,
        "p50_ms": float(np.median(per_scan)) * 1e3, "p99_ms": float(np.percentile(per_scan, 99)) * 1e3,
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, "rms_m": rms,
    }


def measured(laser: str, mode: str) -> dict[str, float]:
    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-m", "benchmarks.slam", "--case", laser, mode], cwd=root,
                         check=True, capture_output=True, text=True)
    return json.loads(out.stdout)  # type: ignore[no-any-return]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--case", nargs=2, metavar=("LASER", "MODE"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.case:
        print(json.dumps(run_case(*args.case)))
        return
    for laser in LASERS:
        slam, odometry = measured(laser, "slam"), measured(laser, "odometry")
        for name, found in (("SLAM", slam), ("odometry-only map", odometry)):
            per_scan = found["cpu_s"] / found["scans"] * 1e3
            print(f"{laser:<10} {name:<18} {found['scans']:5.0f} scans: {per_scan:6.2f} ms CPU/scan "
                  f"(p50 {found['p50_ms']:.2f}, p99 {found['p99_ms']:.2f}), real-time factor "
                  f"{found['data_s'] / found['cpu_s']:7.1f}x, peak RSS {found['peak_rss_mb']:5.0f} MB, "
                  f"trajectory RMS {found['rms_m'] * 100:6.1f} cm", flush=True)
        factor = slam["data_s"] / slam["cpu_s"]
        ratio = slam["cpu_s"] / odometry["cpu_s"]
        verdict = (f"target real-time factor >= {TARGET_REAL_TIME:.0f}x: "
                   f"{'met' if factor >= TARGET_REAL_TIME else 'MISSED'}" if laser == "360x10Hz"
                   else "for comparison")
        print(f"{laser:<10} ratio SLAM / odometry-only CPU {ratio:.1f}, peak RSS "
              f"{slam['peak_rss_mb'] / odometry['peak_rss_mb']:.2f}; {verdict}", flush=True)


if __name__ == "__main__":
    main()
