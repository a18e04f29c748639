"""Real processes on loopback for integration tests: bounded in time, always cleaned up."""

from __future__ import annotations

import argparse
import importlib.util
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

import zenoh

from robot_relay.session import add_zenoh_arguments, open_session, zenoh_options


def open_loopback(*flags: str) -> zenoh.Session:
    """A Zenoh session opened through the commands' own flags, never scouting the network."""
    parser = argparse.ArgumentParser()
    add_zenoh_arguments(parser)
    return open_session(zenoh_options(parser.parse_args(["--no-multicast-scouting", *flags])))


def stop_signals_back() -> None:
    """SIGINT and SIGQUIT back to their defaults where this process inherited them ignored, as a
    background job of a non-interactive shell does (POSIX): the processes it starts inherit an
    ignored signal, and a Rerun viewer, which installs no SIGINT handler of its own, then ignores
    the SIGINT that tells it to finish its saved file."""
    for signum, handler in ((signal.SIGINT, signal.default_int_handler), (signal.SIGQUIT, signal.SIG_DFL)):
        if signal.getsignal(signum) == signal.SIG_IGN:
            signal.signal(signum, handler)


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def command(module: str, *args: str) -> list[str]:
    return [sys.executable, "-m", module, *args]


@contextmanager
def running(cmd: Sequence[str], output: Path | None = None) -> Iterator[subprocess.Popen[str]]:
    """Start ``cmd``, its stdout and stderr piped, or both written to ``output`` (for a process
    whose output nobody reads: a full pipe would stop it); on exit, SIGTERM then SIGKILL whatever
    is still running."""
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    with ExitStack() as files:
        written = None if output is None else files.enter_context(output.open("w"))
        proc = subprocess.Popen(
            list(cmd), stdout=written or subprocess.PIPE,
            stderr=subprocess.STDOUT if written else subprocess.PIPE, text=True, env=env,
        )
        try:
            yield proc
        finally:
            stop(proc)


def stop(process: subprocess.Popen[Any], wait_s: float = 10.0) -> int:
    """SIGTERM, then SIGKILL if ``process`` has not ended within ``wait_s``; its exit code."""
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
    try:
        return process.wait(timeout=wait_s)
    except subprocess.TimeoutExpired:
        process.kill()
        return process.wait(timeout=10)


VIEWER_SAVE_WAIT_S = 60.0


@contextmanager
def saving_viewer(received: Path, startup_s: float = 60.0) -> Iterator[tuple[str, subprocess.Popen[str]]]:
    """A Rerun viewer without a window (the binary itself, so signals reach the server) that
    saves what it receives to ``received``: its URL and process. It writes the file when it gets
    SIGINT, which it gets on leaving if the test has not sent it. Its output goes to
    ``received`` + ``.log``; a viewer that does not end on SIGINT fails the test with its state
    (that state showed SIGINT ignored: the suite had been started as a background job, which
    tests/conftest.py ``pytest_configure`` now undoes)."""
    port = free_port()
    output = received.with_name(received.name + ".log")
    with running([str(rerun_binary()), "--port", str(port), "--save", str(received)], output) as viewer:
        wait_listening(port, startup_s, "the viewer")
        yield f"rerun+http://127.0.0.1:{port}/proxy", viewer
        if viewer.poll() is None:
            viewer.send_signal(signal.SIGINT)
            try:
                viewer.wait(timeout=VIEWER_SAVE_WAIT_S)
            except subprocess.TimeoutExpired:
                raise AssertionError(_stuck_viewer(viewer.pid, port, output)) from None


def _stuck_viewer(pid: int, port: int, output: Path) -> str:
    """What a viewer that did not end on SIGINT was doing: its signal masks and state, the
    connections to its port, its output's tail."""
    status = Path(f"/proc/{pid}/status").read_text(errors="replace").splitlines()
    fields = [line for line in status if line.split(":")[0] in
              {"State", "Threads", "SigPnd", "ShdPnd", "SigBlk", "SigIgn", "SigCgt"}]
    connections = subprocess.run(["ss", "-tn", f"( sport = :{port} or dport = :{port} )"],
                                 capture_output=True, text=True, check=False).stdout
    return (f"the viewer (pid {pid}) did not end within {VIEWER_SAVE_WAIT_S:.0f} s of SIGINT; "
            f"{'; '.join(fields)}\nconnections:\n{connections}"
            f"output ends:\n{output.read_text(errors='replace')[-2000:]}")


def children(parent: int, marker: str) -> list[int]:
    """The running children of process ``parent`` (no zombie) whose command line holds ``marker``."""
    found = subprocess.run(["ps", "-ww", "-o", "pid=,stat=,args=", "--ppid", str(parent)],
                           capture_output=True, text=True, check=False).stdout
    return [int(pid) for pid, state, args in (line.split(None, 2) for line in found.splitlines())
            if marker in args and not state.startswith("Z")]


def converter_processes(host: int) -> list[int]:
    """The children of process ``host`` that convert its heavy topics (host_bridge/pipeline/offload.py)."""
    from host_bridge.pipeline.offload import CHILD_MAIN

    return children(host, CHILD_MAIN)


READER_MAIN = "robot_relay.sources.sqlite_rows"
"""What the command line of a process reading a sqlite3 bag ahead holds (host_bridge/inputs/rows_ahead.py)."""


def alive(pid: int) -> bool:
    return subprocess.run(["kill", "-0", str(pid)], check=False, capture_output=True).returncode == 0


def listening(port: int) -> bool:
    with socket.socket() as sock:
        return sock.connect_ex(("127.0.0.1", port)) == 0


def rerun_binary() -> Path:
    """rerun-sdk's viewer binary, beside its Python wrapper (started itself, signals reach it)."""
    spec = importlib.util.find_spec("rerun_cli")
    assert spec is not None
    assert spec.origin is not None
    return Path(spec.origin).parent / "rerun"


def wait_listening(port: int, seconds: float, what: str) -> None:
    deadline = time.monotonic() + seconds
    while not listening(port):
        assert time.monotonic() < deadline, f"{what} did not listen within {seconds} s"
        time.sleep(0.1)


@contextmanager
def headless_viewer() -> Iterator[tuple[str, int, subprocess.Popen[bytes]]]:
    """A real Rerun gRPC server (``rerun --serve-grpc``, no window): its URL, port and process.
    The binary is started itself, not the ``rerun`` Python wrapper, so killing it kills the
    server."""
    port = free_port()
    proc = subprocess.Popen(
        [str(rerun_binary()), "--serve-grpc", "--port", str(port)],
        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    try:
        wait_listening(port, 30, "rerun --serve-grpc")
        yield f"rerun+http://127.0.0.1:{port}/proxy", port, proc
    finally:
        proc.kill()
        proc.wait(timeout=10)


@contextmanager
def rendering_viewer(startup_s: float = 60.0) -> Iterator[tuple[str, subprocess.Popen[bytes]]]:
    """Rerun's native viewer drawing offscreen (``rerun --headless``: software GL, Mesa's
    lavapipe on a machine without a GPU; no display needed): its URL and process. Skips the test
    when it cannot start (no Vulkan adapter: ``apt-get install mesa-vulkan-drivers``)."""
    import pytest

    port = free_port()
    said = tempfile.TemporaryFile()  # noqa: SIM115 - closed below; a pipe left unread would block it
    proc = subprocess.Popen(
        [str(rerun_binary()), "--headless", "--port", str(port)], stdout=subprocess.DEVNULL, stderr=said,
    )
    try:
        deadline = time.monotonic() + startup_s
        while not listening(port):
            if proc.poll() is not None:
                said.seek(0)
                pytest.skip(f"rerun --headless did not start (no Vulkan adapter? apt-get install "
                            f"mesa-vulkan-drivers): {said.read().decode()[-300:]}")
            assert time.monotonic() < deadline, f"rerun --headless did not listen within {startup_s} s"
            time.sleep(0.1)
        yield f"rerun+http://127.0.0.1:{port}/proxy", proc
    finally:
        proc.kill()
        proc.wait(timeout=10)
        said.close()
