"""Columnar CDR decode (host_bridge/core/columns.py) against rosbags' ``deserialize_cdr`` per message.

Three runs of ``--count`` messages (default 100k) serialized with rosbags, every message with its
own stamp and values: Imu (frame ``imu_link``), JointState (6 joints, frame ``base_link``) and
TFMessage (one transform odom -> base_link). Each is decoded two ways, in alternating rounds:

- baseline: ``typestore.deserialize_cdr(payload, msgtype)`` for every payload, as the host's
  decoder does today (message objects only; building arrays from them would cost more);
- columns: ``read_columns(payloads, msgtype, typestore)``, once over the whole run and once in
  runs of 2048 (the most the bag input hands the dispatcher at once).

Times are CPU seconds of this process (the decode is single-threaded; CPU time is what the
shared machine's other load disturbs least), the median over ``--rounds``; the ratio is
columns messages/s over baseline messages/s, measured in the same run. Before timing, the
columns' stamps and one float field are checked against the baseline's messages.

    .venv/bin/python benchmarks/columns_decode.py [--count 100000] [--rounds 3]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import numpy.typing as npt
from rosbags.typesys import Stores, get_typestore
from rosbags.typesys.store import Typestore

from host_bridge.core.columns import Columns, read_columns

BAG_RUN = 2048  # host_bridge/inputs/bag.py's run_size
JOINTS = ["shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3"]


def _header(store: Typestore, i: int, frame: str) -> Any:
    stamp_type = store.types["builtin_interfaces/msg/Time"]
    stamp = stamp_type(sec=1_700_000_000 + i // 100, nanosec=i % 100 * 10_000_000)
    return store.types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame)


def _imu(store: Typestore, i: int, values: np.random.Generator) -> Any:
    types = store.types
    vector = types["geometry_msgs/msg/Vector3"]
    return types["sensor_msgs/msg/Imu"](
        header=_header(store, i, "imu_link"),
        orientation=types["geometry_msgs/msg/Quaternion"](*values.normal(size=4)),
        orientation_covariance=values.normal(size=9),
        angular_velocity=vector(*values.normal(size=3)),
        angular_velocity_covariance=values.normal(size=9),
        linear_acceleration=vector(*values.normal(size=3)),
        linear_acceleration_covariance=values.normal(size=9),
    )


def _joint_state(store: Typestore, i: int, values: np.random.Generator) -> Any:
    return store.types["sensor_msgs/msg/JointState"](
        header=_header(store, i, "base_link"), name=JOINTS, position=values.normal(size=6),
        velocity=values.normal(size=6), effort=values.normal(size=6),
    )


def _tf(store: Typestore, i: int, values: np.random.Generator) -> Any:
    types = store.types
    transform = types["geometry_msgs/msg/Transform"](
        translation=types["geometry_msgs/msg/Vector3"](*values.normal(size=3)),
        rotation=types["geometry_msgs/msg/Quaternion"](*values.normal(size=4)),
    )
    stamped = types["geometry_msgs/msg/TransformStamped"](
        header=_header(store, i, "odom"), child_frame_id="base_link", transform=transform
    )
    return types["tf2_msgs/msg/TFMessage"](transforms=[stamped])


@dataclass(frozen=True)
class Case:
    """A type to time, with one float field and the stamps read both ways to check the columns."""

    make: Callable[[Typestore, int, np.random.Generator], Any]
    msgtype: str
    float_of_message: Callable[[Any], float]
    float_column: Callable[[Columns], npt.NDArray[np.float64]]
    nanosec_column: Callable[[Columns], npt.NDArray[np.uint32]]


CASES = {
    "Imu": Case(
        _imu, "sensor_msgs/msg/Imu", lambda m: m.angular_velocity.y,
        lambda c: c["angular_velocity.y"], lambda c: c["header.stamp.nanosec"],
    ),
    "JointState (6 joints)": Case(
        _joint_state, "sensor_msgs/msg/JointState", lambda m: m.effort[5],
        lambda c: c["effort"][:, 5], lambda c: c["header.stamp.nanosec"],
    ),
    "TFMessage (1 transform)": Case(
        _tf, "tf2_msgs/msg/TFMessage", lambda m: m.transforms[0].transform.rotation.w,
        lambda c: c["transforms.transform.rotation.w"][:, 0],
        lambda c: c["transforms.header.stamp.nanosec"][:, 0],
    ),
}


def _cpu_seconds(work: Callable[[], object]) -> float:
    start = time.process_time()
    work()
    return time.process_time() - start


def _in_runs(payloads: Sequence[bytes], msgtype: str, store: Typestore) -> None:
    for start in range(0, len(payloads), BAG_RUN):
        if read_columns(payloads[start : start + BAG_RUN], msgtype, store) is None:
            raise SystemExit(f"{msgtype}: a run of {BAG_RUN} was refused")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--count", type=int, default=100_000, help="messages of each type")
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    store = get_typestore(Stores.ROS2_HUMBLE)
    print(f"{args.count} messages of each type, median CPU seconds over {args.rounds} rounds")
    print(f"{'type':<24} {'rosbags msg/s':>14} {'columns msg/s':>14} {'ratio':>7} "
          f"{'runs of 2048 msg/s':>19} {'ratio':>7}")
    for name, case in CASES.items():
        msgtype = case.msgtype
        values = np.random.default_rng(0)
        payloads = [
            bytes(store.serialize_cdr(case.make(store, i, values), msgtype)) for i in range(args.count)
        ]
        messages = [store.deserialize_cdr(payload, msgtype) for payload in payloads]
        columns = read_columns(payloads, msgtype, store)
        if columns is None:
            raise SystemExit(f"{msgtype}: the run was refused")
        if case.float_column(columns).tolist() != [case.float_of_message(m) for m in messages]:
            raise SystemExit(f"{msgtype}: a float column differs from rosbags' values")
        if case.nanosec_column(columns).tolist() != [i % 100 * 10_000_000 for i in range(args.count)]:
            raise SystemExit(f"{msgtype}: the stamps differ from those written")
        timings: dict[str, list[float]] = {"baseline": [], "whole": [], "runs": []}
        for _ in range(args.rounds):
            timings["baseline"].append(
                _cpu_seconds(lambda: [store.deserialize_cdr(p, msgtype) for p in payloads])  # noqa: B023
            )
            timings["whole"].append(_cpu_seconds(lambda: read_columns(payloads, msgtype, store)))  # noqa: B023
            timings["runs"].append(_cpu_seconds(lambda: _in_runs(payloads, msgtype, store)))  # noqa: B023
        rate = {key: args.count / statistics.median(seconds) for key, seconds in timings.items()}
        print(f"{name:<24} {rate['baseline']:>14,.0f} {rate['whole']:>14,.0f} "
              f"{rate['whole'] / rate['baseline']:>6.1f}x {rate['runs']:>19,.0f} "
              f"{rate['runs'] / rate['baseline']:>6.1f}x")


if __name__ == "__main__":
    main()
