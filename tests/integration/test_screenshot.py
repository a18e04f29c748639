"""What a person sees: the demo's recording served by ``swanky-host --serve-web`` and opened in
headless Chromium (software GL) fills every view of Swanky's layout with the demo's data: the
3D view its walls, floor and coloured scan and cloud, the depth image its colormap, the camera
image the rendered room, the odometry plot its lines and the log its rows, where the viewer
without data shows white.

The recording is the demo's own bag (DEMO_SECONDS, the demo's simulation) converted with
``--bag BAG --serve-web``, not a live ``--demo``: software GL on two cores draws the viewer
slower than the live demo streams, so a live page fell further behind with every capture (a
capture took ~50 s at 73 s latency, 190 s in all); a finished recording is taken in once and
the page settles.

Needs a Chromium: ``apt-get install -y --no-install-recommends chromium-headless-shell`` (``.ci/run``
installs it) or ``$SWANKY_CHROMIUM``; skips with that hint otherwise. The picture is kept under
the test's tmp_path (its path is printed; ``pytest -s`` shows it) for a look.
"""

from __future__ import annotations

import importlib.util
import queue
import threading
from pathlib import Path
from types import ModuleType
from typing import IO

import cv2
import numpy as np
import numpy.typing as npt
import pytest

from host_bridge.demo.bag import write_demo_bag
from tests.integration.procs import command, free_port, running
from tests.integration.robot_bags import Lines

SCRIPT = Path(__file__).resolve().parents[2] / "scripts" / "screenshot.py"
SIZE = (1280, 800)
DEMO_SECONDS = 5.0
CAPTURE_S = 70.0
"""The page's captures at most, within the test's ~90 s on a loaded 2-core machine."""

Region = tuple[slice, slice]
# Where Swanky's layout puts each view of one robot at SIZE (Rerun 0.41, its side panels open),
# inside the view's frame: rows, columns. The viewer without data is white in all of them.
VIEW_3D: Region = (slice(65, 595), slice(205, 662))
DEPTH_IMAGE: Region = (slice(86, 200), slice(670, 822))
CAMERA_IMAGE: Region = (slice(86, 200), slice(828, 979))
PLOT: Region = (slice(255, 395), slice(790, 975))
"""The odometry tab, right of its legend."""
LOG_ROWS: Region = (slice(485, 545), slice(685, 965))
"""Below the log's header."""
WALL_GREYS = ((120, 120, 136), (120, 136, 136))
"""RGB of the demo's walls and of the map's free floor as the 3D view shades them."""

pytestmark = pytest.mark.integration


def script(path: Path) -> ModuleType:
    """``scripts/screenshot.py`` (a script, not a package) as a module: the test drives the
    browser itself, capturing until the views show the demo."""
    spec = importlib.util.spec_from_file_location("screenshot", path)
    assert spec is not None
    assert spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


SCREENSHOT = script(SCRIPT)


def browser_or_skip() -> str:
    browser: str | None = SCREENSHOT.find_browser()
    if browser is None:
        pytest.skip(f"no Chromium found: install one with '{SCREENSHOT.INSTALL_HINT}' (.ci/run "
                    "does) or name it with $SWANKY_CHROMIUM")
    return browser


def first_line(stream: IO[str], timeout: float) -> str:
    """The first line of ``stream``, read on a thread so a silent process cannot hang the test."""
    lines: queue.Queue[str] = queue.Queue()
    threading.Thread(target=lambda: lines.put(stream.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout)
    except queue.Empty:
        pytest.fail(f"the host printed nothing within {timeout} s")


def decoded(png: bytes) -> npt.NDArray[np.uint8]:
    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    assert image is not None
    return image.astype(np.uint8, copy=False)


def hsv(image: npt.NDArray[np.uint8], region: Region) -> npt.NDArray[np.uint8]:
    """OpenCV's HSV of ``region``: hue 0-180 (red 0 and 180, yellow 30, green 60, blue 120)."""
    return cv2.cvtColor(np.ascontiguousarray(image[region]), cv2.COLOR_BGR2HSV).astype(np.uint8, copy=False)


def share(mask: npt.NDArray[np.bool_]) -> float:
    return float(np.mean(mask))


def vivid(pixels: npt.NDArray[np.uint8]) -> npt.NDArray[np.bool_]:
    mask: npt.NDArray[np.bool_] = (pixels[..., 1] > 80) & (pixels[..., 2] > 60)
    return mask


def hue_between(pixels: npt.NDArray[np.uint8], low: int, high: int) -> npt.NDArray[np.bool_]:
    mask: npt.NDArray[np.bool_] = vivid(pixels) & (pixels[..., 0] >= low) & (pixels[..., 0] <= high)
    return mask


def what_the_views_show(image: npt.NDArray[np.uint8]) -> dict[str, float]:
    """Shares of each view's pixels in the colours the demo's data draws there."""
    scene, depth, camera = hsv(image, VIEW_3D), hsv(image, DEPTH_IMAGE), hsv(image, CAMERA_IMAGE)
    rgb = image[VIEW_3D][..., ::-1].astype(np.int16)
    walls = np.zeros(rgb.shape[:2], bool)
    for grey in WALL_GREYS:
        walls |= np.all(np.abs(rgb - np.array(grey)) <= 16, axis=-1)
    return {
        "3D walls and floor": share(walls),
        # The scan and the depth cloud, coloured by distance: red, yellow and green points.
        "3D red": share(hue_between(scene, 0, 10) | hue_between(scene, 170, 180)),
        "3D yellow": share(hue_between(scene, 20, 35)),
        "3D green": share(hue_between(scene, 36, 90)),
        # The depth colormap: the far wall red, the floor in front blue.
        "depth image coloured": share(vivid(depth)),
        "depth image red": share(hue_between(depth, 0, 10) | hue_between(depth, 170, 180)),
        "depth image blue": share(hue_between(depth, 100, 130)),
        # The rendered room: beige walls and a brown floor, shaded.
        "camera image brown": share((camera[..., 0] >= 5) & (camera[..., 0] <= 30) & (camera[..., 1] >= 30)),
        "camera image contrast": float(image[CAMERA_IMAGE].std()) / 255,
        "plot lines": share(vivid(hsv(image, PLOT))),
        "log text": share(np.all(image[LOG_ROWS] < 120, axis=-1)),
    }


# The smallest share each must reach. The drawn demo (its 5 s and 10 s bags and a live --demo
# page, each at its last moment) gave 6-13 %, 3.1-3.6 %, 0.75-0.9 %, 0.6-1.0 %, 100 %,
# 17-33 %, 37-49 %, 58-84 %, 0.13-0.14, 1.4 % and 5-7 %; the viewer without data 0 for each,
# and a page that had taken in 193 of the recording's 5886 rows missed 7 of them.
EXPECTED = {
    "3D walls and floor": 0.03,
    "3D red": 0.005,
    "3D yellow": 0.001,
    "3D green": 0.001,
    "depth image coloured": 0.9,
    "depth image red": 0.05,
    "depth image blue": 0.05,
    "camera image brown": 0.4,
    "camera image contrast": 0.05,
    "plot lines": 0.003,
    "log text": 0.01,
}


def unshown(image: npt.NDArray[np.uint8]) -> dict[str, str]:
    """What of EXPECTED the picture lacks, with the share it has."""
    shown = what_the_views_show(image)
    return {name: f"{shown[name]:.4f} < {least}" for name, least in EXPECTED.items()
            if shown[name] < least}


def test_web_viewer_draws_the_demo_in_every_view(tmp_path: Path) -> None:
    browser = browser_or_skip()
    bag = write_demo_bag(tmp_path / "demo", DEMO_SECONDS)
    # --slam: what --demo shows, the map the host builds (the simulated robot publishes none).
    host_cmd = command("host_bridge.cli", "--bag", str(bag), "--robot", "sim", "--slam", "--serve-web",
                       "--web-port", str(free_port()), "--grpc-port", str(free_port()))
    with running(host_cmd) as host:
        assert host.stdout is not None
        line = first_line(host.stdout, timeout=60)
        assert line.startswith("Rerun web viewer: http://127.0.0.1:"), line
        url = line.split(": ", 1)[1].strip()
        Lines(host).wait_for("bag converted; serving the web viewer until Ctrl-C", timeout=60)
        png: bytes = SCREENSHOT.capture(url, browser=browser, size=SIZE, timeout=CAPTURE_S,
                                        drawn=lambda shot: not unshown(decoded(shot)))
    picture = tmp_path / "demo.png"
    picture.write_bytes(png)
    print(f"screenshot of the demo: {picture}")
    image = decoded(png)
    assert image.shape == (SIZE[1], SIZE[0], 3)
    missing = unshown(image)
    assert not missing, (
        f"{picture}: views without the demo's data: {missing}; all: {what_the_views_show(image)}"
    )
