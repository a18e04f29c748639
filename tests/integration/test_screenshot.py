"""What a person sees: ``swanky-host --demo --serve-web`` opened in headless Chromium (software
GL) draws the demo in Swanky's layout, not an empty viewer.

Needs a Chromium: ``apt-get install -y --no-install-recommends chromium-headless-shell`` (or
``$SWANKY_CHROMIUM``); skips with that hint otherwise. The picture is kept under the test's
tmp_path (its path is printed; ``pytest -s`` shows it) for a look.
"""

from __future__ import annotations

import queue
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO

import cv2
import numpy as np
import pytest

from tests.integration.procs import command, free_port, running

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "screenshot.py"
SIZE = (1280, 800)
# Between the viewer's side panels at SIZE (Rerun 0.41): the views, where the demo must show.
VIEWPORT = (slice(40, 600), slice(200, 980))

pytestmark = pytest.mark.integration


def browser_or_skip() -> str:
    found = subprocess.run([sys.executable, str(SCRIPT), "--check"], capture_output=True,
                           text=True, timeout=30, check=False)
    if found.returncode != 0:
        pytest.skip(found.stderr.strip())
    return found.stdout.strip()


def first_line(stream: IO[str], timeout: float) -> str:
    """The first line of ``stream``, read on a thread so a silent process cannot hang the test."""
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: lines.put(stream.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout)
    except queue.Empty:
        pytest.fail(f"the host printed nothing within {timeout} s")


def drain(stream: IO[str]) -> None:
    """Keep reading a pipe so the process never blocks on it."""
    threading.Thread(target=lambda: [None for _ in stream], daemon=True).start()


def test_web_viewer_draws_the_demo(tmp_path: Path) -> None:
    browser_or_skip()
    web, grpc = free_port(), free_port()
    host_cmd = command("host_bridge.cli", "--demo", "--serve-web", "--web-port", str(web),
                       "--grpc-port", str(grpc), "--duration", "300")
    with running(host_cmd) as host:
        assert host.stdout is not None
        assert host.stderr is not None
        drain(host.stderr)
        line = first_line(host.stdout, timeout=60)
        assert line.startswith("Rerun web viewer: http://127.0.0.1:"), line
        url = line.split(": ", 1)[1].strip()
        picture = tmp_path / "demo.png"
        shot = subprocess.run(
            [sys.executable, str(SCRIPT), url, str(picture), "--size", "x".join(map(str, SIZE)),
             "--timeout", "150", "--min-colours", "3000"],
            capture_output=True, text=True, timeout=240, check=False,
        )
    assert shot.returncode == 0, shot.stderr
    print(f"screenshot of the demo: {picture}")

    image = cv2.imread(str(picture))
    assert image is not None
    assert image.shape == (SIZE[1], SIZE[0], 3)
    colours = np.unique(image.reshape(-1, 3), axis=0).shape[0]
    hsv = cv2.cvtColor(image[VIEWPORT], cv2.COLOR_BGR2HSV)
    vivid = float(np.mean((hsv[..., 1] > 80) & (hsv[..., 2] > 60)))
    # The viewer with no data drawn is grey on white: ~1000 colours and no vivid pixel between
    # the panels. The demo adds the camera images, the depth colormap and the rainbow scan.
    assert colours > 2000, f"{picture}: only {colours} colours"
    assert vivid > 0.01, f"{picture}: only {vivid:.2%} vivid pixels in the views"
