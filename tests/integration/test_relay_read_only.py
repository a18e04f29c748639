"""The relay is read-only towards ROS: nothing arriving over Zenoh publishes into the robot's ROS
graph, calls a service or runs code.

Live: ``swanky-relay`` runs against a real rclpy graph (ROS 2 Jazzy, Fast DDS, the ``[ros-test]``
wheels; loopback, a private ``ROS_DOMAIN_ID``) in which this test's node publishes ``/chatter``
and watches ``/chatter`` and ``/cmd_vel``. A Zenoh client connected to the relay then puts,
deletes and queries on every swanky key and wildcard, on rmw_zenoh data, service and liveliness
keys, and declares publishers and liveliness tokens there. rclpy is asked what the relay's node
has before and after (publishers, subscriptions, service servers and clients) and which topics
and publishers the graph holds; the test's own subscribers count what arrives.

Static: no module of robot_relay calls what could write into ROS or run code it is sent.
"""

from __future__ import annotations

import ast
import importlib.util
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import zenoh

from robot_relay.wire import Attachment, catalog_key, data_key
from tests.integration.procs import command, free_port, open_loopback, running
from tests.integration.robot_bags import Lines
from tests.integration.test_ros2_live import ros_environment  # noqa: F401  (a fixture)
from tests.reliability import Record

pytestmark = pytest.mark.integration

RELAY_PACKAGE = Path(__file__).resolve().parents[2] / "robot_relay"
ROBOT = "tb"
RELAY_NODE = "swanky_relay"
CHATTER_HZ = 20
# Every node has these from rclpy itself: its log, parameter events, and the parameter and
# type-description services (answered from the node's own parameters; the relay reads none).
NODE_PUBLISHERS = {"/rosout", "/parameter_events"}
NODE_SERVICES = {f"/{RELAY_NODE}/{name}" for name in (
    "describe_parameters", "get_parameter_types", "get_parameters", "get_type_description",
    "list_parameters", "set_parameters", "set_parameters_atomically",
)}
# After the last write, how long the relay gets to do something about it: several of its
# graph reads (one a second) and DDS discovery on loopback.
GRACE_S = 4.0
TWIST_TYPE = "geometry_msgs::msg::dds_::Twist_"
STRING_TYPE = "std_msgs::msg::dds_::String_"
HASH = "RIHS01_" + "0" * 64
RMW_KEYS = (  # rmw_zenoh's <domain>/<topic>/<type>/<hash> data and service keys, domain 0 and ours
    f"0/cmd_vel/{TWIST_TYPE}/{HASH}",
    f"0/chatter/{STRING_TYPE}/{HASH}",
    f"0/tb/cmd_vel/{TWIST_TYPE}/{HASH}",
    f"0/{RELAY_NODE}/set_parameters/rcl_interfaces::srv::dds_::SetParameters_/{HASH}",
    f"0/{RELAY_NODE}/get_parameters/rcl_interfaces::srv::dds_::GetParameters_/{HASH}",
    "0/**",
    "*/**",
)
SWANKY_KEYS = (
    data_key(ROBOT, "/chatter"),  # the very key the relay publishes the robot's topic on
    data_key(ROBOT, "/cmd_vel"),
    data_key(ROBOT, "/rosout"),
    data_key(ROBOT, "/parameter_events"),
    catalog_key(ROBOT),
    f"swanky/{ROBOT}/alive",
    f"swanky/{ROBOT}/stats",
    f"swanky/{ROBOT}/files/std_msgs/package.xml",
    f"swanky/{ROBOT}/data/**",
    f"swanky/{ROBOT}/**",
    "swanky/*/data/*",
    "swanky/**",
    "**",
)
LIVELINESS_TOKENS = (  # an rmw_zenoh publisher and service server announced, and a fake relay
    f"@ros2_lv/0/0123456789abcdef/0/1/MP/%/%/cmd_vel/{TWIST_TYPE}/{HASH}/::,10:,:,:,,",
    f"@ros2_lv/0/0123456789abcdef/0/2/SS/%/%/{RELAY_NODE}%set_parameters/"
    f"rcl_interfaces::srv::dds_::SetParameters_/{HASH}/::,10:,:,:,,",
    f"swanky/{ROBOT}/alive",
)


@dataclass(frozen=True)
class NodeGraph:
    """What rclpy says the relay's node has, and the graph's topics with their publisher counts."""

    publishers: frozenset[str]
    subscriptions: frozenset[str]
    services: frozenset[str]
    clients: frozenset[str]
    topics: dict[str, tuple[tuple[str, ...], int]]


class Observer:
    """This test's ROS node: publishes /chatter, counts what arrives on /chatter and /cmd_vel,
    reads the graph. Its own rclpy context, shut down at the end."""

    def __init__(self) -> None:
        import rclpy
        from geometry_msgs.msg import Twist
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions
        from std_msgs.msg import String

        self.context = Context()
        rclpy.init(context=self.context, signal_handler_options=SignalHandlerOptions.NO)
        self.node: Any = rclpy.create_node("robot", context=self.context)
        self.published: list[str] = []
        self.chatter: list[str] = []
        self.cmd_vel: list[Any] = []
        publisher = self.node.create_publisher(String, "/chatter", 10)

        def publish() -> None:
            text = f"robot {len(self.published)}"
            publisher.publish(String(data=text))
            self.published.append(text)

        self.node.create_timer(1 / CHATTER_HZ, publish)
        def heard(message: Any) -> None:
            self.chatter.append(message.data)

        self.node.create_subscription(String, "/chatter", heard, 10)
        self.node.create_subscription(Twist, "/cmd_vel", self.cmd_vel.append, 10)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._spin, name="observer", daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        while not self._stop.is_set():
            self.executor.spin_once(timeout_sec=0.05)

    def relay_graph(self) -> NodeGraph:
        node = self.node

        def names(pairs: list[tuple[str, list[str]]]) -> frozenset[str]:
            return frozenset(name for name, _ in pairs)

        topics = {name: (tuple(types), node.count_publishers(name))
                  for name, types in node.get_topic_names_and_types()}
        return NodeGraph(
            names(node.get_publisher_names_and_types_by_node(RELAY_NODE, "/")),
            names(node.get_subscriber_names_and_types_by_node(RELAY_NODE, "/")),
            names(node.get_service_names_and_types_by_node(RELAY_NODE, "/")),
            names(node.get_client_names_and_types_by_node(RELAY_NODE, "/")),
            topics,
        )

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)
        self.executor.shutdown()
        self.node.destroy_node()
        self.context.try_shutdown()


def wait_until(condition: Any, what: str, timeout: float = 60) -> Any:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.1)
    raise AssertionError(f"{what} within {timeout} s")


def attack(session: zenoh.Session, cdr: bytes) -> int:
    """Every write and call a Zenoh client can aim at the relay and the robot; how many."""
    attachment = Attachment(sequence=1, receive_ns=time.time_ns()).pack()
    tried = 0
    for key in SWANKY_KEYS + RMW_KEYS:
        session.put(key, cdr, attachment=attachment,
                    encoding=zenoh.Encoding.APPLICATION_CDR.with_schema("geometry_msgs/msg/Twist"))
        session.delete(key)
        list(session.get(key, payload=cdr, attachment=attachment, timeout=1.0))
        tried += 3
    list(session.get("@/**", timeout=1.0))  # the relay session's admin space: read-only
    tried += 1
    entities: list[Any] = [session.liveliness().declare_token(key) for key in LIVELINESS_TOKENS]
    for key in (data_key(ROBOT, "/cmd_vel"), f"0/cmd_vel/{TWIST_TYPE}/{HASH}"):
        publisher = session.declare_publisher(key)
        for _ in range(10):
            publisher.put(cdr, attachment=attachment)
        entities.append(publisher)
        tried += 10
    tried += len(LIVELINESS_TOKENS)
    # Declared for a while (the relay reads the ROS graph once a second), then undeclared.
    time.sleep(GRACE_S / 2)
    for entity in entities:
        entity.undeclare()
    return tried


@pytest.fixture
def observer(ros_environment: None) -> Iterator[Observer]:  # noqa: F811
    if importlib.util.find_spec("rclpy") is None:
        pytest.skip("rclpy is not installed: pip install -e '.[ros-test]' (the ros-jazzy wheels "
                    "exist for CPython 3.11 on x86-64 Linux only)")
    ros = Observer()
    yield ros
    ros.close()


def test_zenoh_clients_cannot_write_into_the_ros_graph(
    observer: Observer, reliability: Record
) -> None:
    from geometry_msgs.msg import Twist
    from rclpy.serialization import serialize_message

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with running(command("robot_relay.cli", "--robot", ROBOT, "-l", endpoint,
                         "--no-multicast-scouting")) as relay:
        lines = Lines(relay)
        session = open_loopback("-e", endpoint)
        try:
            forwarded: list[bytes] = []
            session.declare_subscriber(data_key(ROBOT, "/chatter"),
                                       lambda s: forwarded.append(s.payload.to_bytes()))
            wait_until(lambda: len(forwarded) >= 3, "/chatter forwarded by the relay")
            # Once discovery has shown all of the relay's node.
            before = wait_until(
                lambda: (g := observer.relay_graph()).publishers == NODE_PUBLISHERS
                and g.services == NODE_SERVICES and "/chatter" in g.subscriptions and g,
                "the relay's node in the graph")
            cmd_vel = bytes(serialize_message(Twist()))
            tried = attack(session, cmd_vel)
            forwarded_at_attack = len(forwarded)
            time.sleep(GRACE_S)
            after = observer.relay_graph()
            # Still relaying: the attack cost it nothing.
            wait_until(lambda: len(forwarded) > forwarded_at_attack + CHATTER_HZ,
                       "/chatter still forwarded after the attack")
        finally:
            session.close()
        assert relay.poll() is None, lines.text
    assert "Traceback" not in lines.text

    assert before.publishers == after.publishers == NODE_PUBLISHERS
    assert before.services == after.services == NODE_SERVICES
    assert before.clients == after.clients == frozenset()
    assert after.subscriptions <= {"/chatter", "/rosout"}
    assert after.topics == before.topics  # no topic appeared, no publisher was added
    assert before.topics["/chatter"] == (("std_msgs/msg/String",), 1)  # this test's publisher
    assert after.topics["/cmd_vel"] == (("geometry_msgs/msg/Twist",), 0)  # this test's subscriber
    assert observer.cmd_vel == []
    # Everything received on /chatter is what this test published, in order.
    assert observer.chatter == observer.published[:len(observer.chatter)]
    assert len(observer.chatter) >= 3 * CHATTER_HZ
    reliability(
        "Security", "a Zenoh client writes and calls into the relay's robot (read-only relay)",
        tried=f"{tried} writes/calls: put, delete and query on {len(SWANKY_KEYS)} swanky keys and "
        f"wildcards and {len(RMW_KEYS)} rmw_zenoh data/service keys, 20 puts from declared "
        f"publishers, {len(LIVELINESS_TOKENS)} liveliness tokens",
        survived=f"the relay's node: publishers {sorted(after.publishers)}, 0 service clients, "
        f"{len(after.services)} (rclpy's parameter) services, as before; 0 new topics or "
        f"publishers; 0 messages on /cmd_vel; {len(observer.chatter)} /chatter messages all "
        "from the robot; the relay kept forwarding",
        lost="0")


# What would open a way into ROS (publish, serve, call a service or action) or run what it is
# given: methods by name, builtins, module functions, modules.
ROS_WRITERS = frozenset({"create_publisher", "create_service", "create_client", "ActionClient",
                         "ActionServer"})
RUNNERS = frozenset({"eval", "exec", "compile", "__import__"})
MODULE_RUNNERS = {"os": ("system", "popen", "exec", "spawn", "posix_spawn"),
                  "yaml": ("load", "unsafe_load", "full_load")}
FORBIDDEN_MODULES = frozenset({"pickle", "marshal", "shelve", "dill", "subprocess"})


def offences(path: Path) -> list[str]:
    """``file:line: what`` for each call or import in ``path`` that could write into ROS or run
    code; ``yaml.safe_load`` and ``re.compile`` are fine."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    found: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else getattr(func, "id", "")
            owner = func.value.id if isinstance(func, ast.Attribute) and isinstance(
                func.value, ast.Name) else ""
            if (name in ROS_WRITERS or (isinstance(func, ast.Name) and name in RUNNERS)
                    or name.startswith(MODULE_RUNNERS.get(owner, ()))):
                found.append((node.lineno, f"calls {owner + '.' if owner else ''}{name}"))
        elif isinstance(node, ast.Import | ast.ImportFrom):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            found.extend((node.lineno, f"imports {m}") for m in modules
                         if m.split(".")[0] in FORBIDDEN_MODULES)
    return [f"{path.name}:{line}: {what}" for line, what in sorted(found)]


def test_relay_code_never_publishes_into_ros_nor_runs_what_it_receives() -> None:
    files = sorted(RELAY_PACKAGE.rglob("*.py"))
    assert {"relay.py", "files.py", "ros2.py", "session.py"} <= {f.name for f in files}
    assert [o for f in files for o in offences(f)] == []


def test_scan_finds_each_forbidden_call(tmp_path: Path) -> None:
    bad = tmp_path / "bad.py"
    bad.write_text(
        "import pickle\nimport yaml\nfrom subprocess import run\n"
        "node.create_publisher(String, '/cmd_vel', 10)\nnode.create_client(Srv, 's')\n"
        "eval(x)\nexec(y)\nyaml.load(z)\nos.system(c)\n"
        "yaml.safe_load(ok)\nre.compile(ok)\njson.loads(ok)\nnode.create_subscription(ok)\n"
    )
    assert offences(bad) == [
        "bad.py:1: imports pickle", "bad.py:3: imports subprocess",
        "bad.py:4: calls node.create_publisher", "bad.py:5: calls node.create_client",
        "bad.py:6: calls eval", "bad.py:7: calls exec", "bad.py:8: calls yaml.load",
        "bad.py:9: calls os.system",
    ]
