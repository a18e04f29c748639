"""First contact with a user's machine: each mistake or busy resource is one ``error:`` line
naming the flag and what to do, exit 2, before anything is converted or opened."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from host_bridge import cli
from host_bridge.outputs.sink import VIEWER_PORT
from robot_relay import cli as relay_cli
from tests.integration.procs import free_port
from tests.integration.robot_bags import Entry, joint_state, tf_message, transform, write_bag

pytestmark = pytest.mark.usefixtures("keep_signal_handlers")  # main() installs its own


@pytest.fixture
def bag(tmp_path: Path) -> Path:
    """A robot's bag: its wheel joints and odometry frame for a second."""
    entries = [
        Entry("/joint_states", "sensor_msgs/msg/JointState", i * 10**8, joint_state(i * 10**8, [i, -i]))
        for i in range(10)
    ] + [
        Entry("/tf", "tf2_msgs/msg/TFMessage", i * 10**8,
              tf_message(transform(i * 10**8, "odom", "base_footprint", (0.1 * i, 0.0, 0.0))))
        for i in range(10)
    ]
    return write_bag(tmp_path / "robot_bag", entries)


def run_host(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str], str]:
    """Exit code, stderr lines and stdout of ``swanky-host ARGV`` run in this process."""
    code = cli.main(list(argv))
    out, err = capsys.readouterr()
    return code, err.strip().splitlines(), out


def listening_socket() -> socket.socket:
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    return sock


@pytest.mark.parametrize("source", ["bag", "demo"])
def test_rerun_addr_without_a_viewer_is_named_before_converting(
    capsys: pytest.CaptureFixture[str], bag: Path, source: str
) -> None:
    port = free_port()
    url = f"rerun+http://127.0.0.1:{port}/proxy"
    args = ["--bag", str(bag)] if source == "bag" else ["--demo", "--duration", "3"]
    started = time.monotonic()
    code, err, out = run_host(capsys, *args, "--rerun-addr", url)
    assert time.monotonic() - started < 10
    assert (code, err, out) == (2, [
        f"swanky-host: error: --rerun-addr {url}: no Rerun viewer at 127.0.0.1:{port}: "
        f"Connection refused; start one (`rerun` listens on port {VIEWER_PORT}) or use --spawn, "
        "--save FILE.rrd or --serve-web"
    ], "")


def test_rerun_addr_where_no_viewer_answers(capsys: pytest.CaptureFixture[str], bag: Path) -> None:
    """E.g. the web viewer's page port given instead of the viewer's: it accepts connections."""
    with listening_socket() as not_a_viewer:
        port = not_a_viewer.getsockname()[1]
        url = f"rerun+http://127.0.0.1:{port}/proxy"
        assert run_host(capsys, "--bag", str(bag), "--rerun-addr", url) == (2, [
            f"swanky-host: error: --rerun-addr {url}: no Rerun viewer at 127.0.0.1:{port}: "
            "something listens there but does not answer as a Rerun viewer (gRPC); start one "
            f"(`rerun` listens on port {VIEWER_PORT}) or use --spawn, --save FILE.rrd or --serve-web"
        ], "")


@pytest.mark.parametrize(
    "url", ["http://127.0.0.1:9876/proxy", "rerun+http://127.0.0.1:9876", "rerun+http://:9876/proxy"]
)
def test_rerun_addr_that_is_no_viewer_url(
    capsys: pytest.CaptureFixture[str], bag: Path, url: str
) -> None:
    assert run_host(capsys, "--bag", str(bag), "--rerun-addr", url) == (2, [
        f"swanky-host: error: --rerun-addr {url}: not a Rerun viewer URL "
        "(e.g. rerun+http://127.0.0.1:9876/proxy)"
    ], "")


@pytest.mark.parametrize("busy", ["--grpc-port", "--web-port"])
def test_serve_web_on_a_busy_port_names_the_flag(
    capsys: pytest.CaptureFixture[str], bag: Path, busy: str
) -> None:
    with listening_socket() as taken:
        port = taken.getsockname()[1]
        ports = {"--grpc-port": str(free_port()), "--web-port": str(free_port()), busy: str(port)}
        code, err, out = run_host(
            capsys, "--bag", str(bag), "--serve-web", *[x for kv in ports.items() for x in kv]
        )
    assert (code, err, out) == (2, [
        f"swanky-host: error: --serve-web: port {port} is in use by another program; choose "
        f"another with {busy} N"
    ], "")


@pytest.mark.parametrize(
    ("address", "message"),
    [
        ("localhost", "--web-bind 'localhost': not an IP address (e.g. 127.0.0.1, 0.0.0.0, ::)"),
        ("192.0.2.1", "--serve-web: cannot listen on 192.0.2.1:{port} (Cannot assign requested "
         "address); check --web-bind"),
    ],
)
def test_web_bind_that_cannot_be_used(
    capsys: pytest.CaptureFixture[str], bag: Path, address: str, message: str
) -> None:
    grpc = free_port()
    code, err, out = run_host(
        capsys, "--bag", str(bag), "--serve-web", "--grpc-port", str(grpc),
        "--web-port", str(free_port()), "--web-bind", address,
    )
    assert (code, err, out) == (2, [f"swanky-host: error: {message.format(port=grpc)}"], "")


def test_host_package_path_to_no_directory(
    capsys: pytest.CaptureFixture[str], bag: Path, tmp_path: Path
) -> None:
    missing = tmp_path / "no" / "such"
    code, err, out = run_host(
        capsys, "--bag", str(bag), "--save", str(tmp_path / "out.rrd"),
        "--package-path", f"robot_description={missing}",
    )
    assert (code, err, out) == (2, [
        f"swanky-host: error: --package-path robot_description={missing}: {missing} is not a "
        "directory (nothing is there)"
    ], "")
    assert not (tmp_path / "out.rrd").exists()


def test_relay_package_path_to_a_file(
    capsys: pytest.CaptureFixture[str], bag: Path, tmp_path: Path
) -> None:
    a_file = tmp_path / "model.urdf"
    a_file.write_text("<robot name='r'/>", encoding="utf-8")
    code = relay_cli.main([
        "--bag", str(bag), "--robot", "r", "--package-path", f"pkg={a_file}",
        "--no-multicast-scouting", "-l", f"tcp/127.0.0.1:{free_port()}",
    ])
    err = capsys.readouterr().err
    assert code == 2
    assert err.strip().splitlines()[-1] == (
        f"swanky-relay: error: --package-path pkg={a_file}: {a_file} is not a directory"
    )


def listen_address(port: int) -> str | None:
    """The local address a TCP socket of this machine listens on at ``port`` (/proc/net/tcp)."""
    for line in Path("/proc/net/tcp").read_text(encoding="ascii").splitlines()[1:]:
        local, state = line.split()[1], line.split()[3]
        host_hex, port_hex = local.split(":")
        if state == "0A" and int(port_hex, 16) == port:  # 0A: LISTEN
            return socket.inet_ntoa(bytes.fromhex(host_hex)[::-1])
    return None


def listen_addresses(ports: list[int], timeout: float) -> dict[int, str | None]:
    """Where each port listens, once all do (Rerun starts its servers on threads of their own)."""
    deadline = time.monotonic() + timeout
    while True:
        bound = {port: listen_address(port) for port in ports}
        if None not in bound.values() or time.monotonic() > deadline:
            return bound
        time.sleep(0.1)


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="reads Linux's /proc/net/tcp")
@pytest.mark.parametrize(
    ("flags", "recording_on"), [((), "127.0.0.1"), (("--web-bind", "0.0.0.0"), "0.0.0.0")]
)
def test_web_viewer_serves_the_recording_on_loopback_unless_told(
    bag: Path, flags: tuple[str, ...], recording_on: str
) -> None:
    grpc, web = free_port(), free_port()
    host = subprocess.Popen(
        [sys.executable, "-m", "host_bridge.cli", "--bag", str(bag), "--serve-web",
         "--grpc-port", str(grpc), "--web-port", str(web), "--duration", "60", *flags],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        assert host.stdout is not None
        url = host.stdout.readline().strip()
        bound = listen_addresses([grpc, web], timeout=30)
        host.send_signal(signal.SIGTERM)
        _, err = host.communicate(timeout=30)
    finally:
        host.kill()
    assert url == f"Rerun web viewer: http://127.0.0.1:{web}/?url=rerun+http://127.0.0.1:{grpc}/proxy"
    assert bound == {grpc: recording_on, web: "0.0.0.0"}  # Rerun's page server: every interface
    note = (
        f"swanky-host: the recording is served on 127.0.0.1:{grpc} only (--web-bind 0.0.0.0 "
        f"opens it to the network); Rerun serves the viewer page (code, no data) on port {web} "
        "of every interface"
    ) if recording_on == "127.0.0.1" else (
        f"swanky-host: the recording (port {grpc}) and the viewer page (port {web}) are open to "
        "every network interface (--web-bind); from another machine use this PC's address "
        "instead of 127.0.0.1"
    )
    assert note in err.splitlines()
    assert host.returncode == 0, err
    assert "Traceback" not in err


@pytest.mark.parametrize("name", ["east/1", "", " east", "east 1"])
def test_a_host_name_that_is_no_entity_path_part(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, name: str,
) -> None:
    with pytest.raises(SystemExit) as exited:
        cli.main(["--host-name", name, "--save", str(tmp_path / "out.rrd")])
    assert exited.value.code == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"swanky-host: error: argument --host-name: {name!r} is not a host name: one word of an "
        "entity path, without '/' or spaces")


def test_a_host_name_reaches_the_options() -> None:
    parsed = cli.parse_args(["--host-name", "east", "--recording-id", "fleet"])
    assert cli.host_options(parsed).host_name == "east"
