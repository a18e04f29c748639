"""Screenshot of a web page in headless Chromium, driven over the DevTools pipe (no extra packages).

Made for Rerun's web viewer (``swanky-host --serve-web``): a WebAssembly app that draws with
WebGL/WebGPU, so it needs software GL (SwiftShader) and some seconds before the first useful
frame. The page is captured every ``--every`` seconds until ``--settle`` captures in a row look
alike (the viewer has loaded and drawn its views) or ``--timeout`` runs out; the last capture is
written.

    python scripts/screenshot.py URL out.png [--browser PATH] [--size 1280x800]

The browser is Debian's ``chromium-headless-shell`` (or ``chromium``):
``apt-get install -y --no-install-recommends chromium-headless-shell``. Exit status 3 means no
browser was found; ``--check`` only looks for one.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import itertools
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import IO, Any

BROWSERS = ("chromium-headless-shell", "chromium", "chromium-browser", "google-chrome")
NO_BROWSER = 3

# Software GL, and none of Chromium's own network traffic: this machine reaches no Google host.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--no-first-run",
    "--hide-scrollbars",
    "--mute-audio",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
    "--ignore-gpu-blocklist",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
    "--disable-dev-shm-usage",
    "--remote-debugging-pipe",
)


def find_browser(explicit: str | None = None) -> str | None:
    """The Chromium to use: ``explicit``, ``$SWANKY_CHROMIUM``, or the first of BROWSERS on PATH."""
    for name in (explicit, os.environ.get("SWANKY_CHROMIUM"), *BROWSERS):
        if name:
            found = shutil.which(name)
            if found:
                return found
    return None


def _high_pipe() -> tuple[int, int]:
    import fcntl

    ends = []
    for fd in os.pipe():
        ends.append(fcntl.fcntl(fd, fcntl.F_DUPFD_CLOEXEC, 10))
        os.close(fd)
    return ends[0], ends[1]


class DevTools:
    """Chrome DevTools Protocol over ``--remote-debugging-pipe``: NUL-separated JSON on fds 3/4."""

    def __init__(self, browser: str, profile: Path, log: IO[bytes]) -> None:
        # Pipe ends numbered 10 and up (bash, not dash, takes such numbers), so moving them to
        # fds 3/4 never overwrites one.
        command_r, self._to_browser = _high_pipe()
        self._from_browser, reply_w = _high_pipe()
        # The browser reads commands on fd 3 and writes replies on fd 4.
        shell = f'exec "$@" 3<&{command_r} 4>&{reply_w}'
        self.process = subprocess.Popen(
            ["bash", "-c", shell, "bash", browser, *CHROMIUM_FLAGS, f"--user-data-dir={profile}",
             "about:blank"],
            stdin=subprocess.DEVNULL, stdout=log, stderr=log, pass_fds=(command_r, reply_w),
        )
        os.close(command_r)
        os.close(reply_w)
        self._ids = itertools.count(1)
        self._buffer = b""

    def call(self, method: str, session: str | None = None, timeout: float = 60.0,
             **params: Any) -> dict[str, Any]:
        ident = next(self._ids)
        message: dict[str, Any] = {"id": ident, "method": method, "params": params}
        if session is not None:
            message["sessionId"] = session
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        deadline = time.monotonic() + timeout
        while True:
            reply = self._next(deadline)
            if reply.get("id") == ident:
                if "error" in reply:
                    msg = f"{method}: {reply['error']}"
                    raise RuntimeError(msg)
                result: dict[str, Any] = reply.get("result", {})
                return result

    def _next(self, deadline: float) -> dict[str, Any]:
        import select

        while b"\0" not in self._buffer:
            left = deadline - time.monotonic()
            ready, _, _ = select.select([self._from_browser], [], [], max(left, 0.0))
            if not ready:
                msg = "the browser did not answer in time"
                raise TimeoutError(msg)
            chunk = os.read(self._from_browser, 1 << 20)
            if not chunk:
                msg = f"the browser exited (status {self.process.poll()})"
                raise RuntimeError(msg)
            self._buffer += chunk
        raw, self._buffer = self._buffer.split(b"\0", 1)
        parsed: dict[str, Any] = json.loads(raw)
        return parsed

    def close(self) -> None:
        with contextlib.suppress(RuntimeError, TimeoutError, OSError):
            self.call("Browser.close", timeout=5.0)
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait(timeout=10)
        os.close(self._to_browser)
        os.close(self._from_browser)


def distinct_colours(png: bytes) -> int:
    """How many different colours the picture has (a blank or loading page has a handful)."""
    import cv2
    import numpy as np

    image = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    if image is None:
        return 0
    packed = image.reshape(-1, 3).astype(np.uint32) @ np.array([1 << 16, 1 << 8, 1], np.uint32)
    return int(np.unique(packed).size)


def capture(
    url: str, *, browser: str, size: tuple[int, int] = (1280, 800), timeout: float = 90.0,
    every: float = 3.0, settle: int = 3, min_colours: int = 200, log: IO[bytes] | None = None,
    drawn: Callable[[bytes], bool] | None = None,
) -> bytes:
    """PNG of ``url`` once it has drawn: ``settle`` captures in a row with at least
    ``min_colours`` colours and nearly the same count, else the last capture at ``timeout``.
    ``drawn`` replaces that guess where the caller knows what the page must show: the first
    capture it accepts.

    Software GL on a busy machine can take tens of seconds per frame, so a capture that does not
    come back in time ends the wait with the previous one instead of failing.
    """
    with tempfile.TemporaryDirectory(prefix="swanky-chromium-") as profile:
        tools = DevTools(browser, Path(profile), log or subprocess.DEVNULL)  # type: ignore[arg-type]
        try:
            target = tools.call("Target.createTarget", url="about:blank")["targetId"]
            session = tools.call("Target.attachToTarget", targetId=target, flatten=True)["sessionId"]
            width, height = size
            tools.call("Emulation.setDeviceMetricsOverride", session, width=width, height=height,
                       deviceScaleFactor=1, mobile=False)
            started = time.monotonic()
            deadline = started + timeout
            tools.call("Page.navigate", session, url=url)
            shot = b""
            counts: list[int] = []
            while True:
                time.sleep(every)
                try:
                    reply = tools.call("Page.captureScreenshot", session,
                                       timeout=max(deadline - time.monotonic(), every), format="png")
                except TimeoutError:
                    if shot:
                        return shot
                    raise
                shot = base64.b64decode(reply["data"])
                counts.append(distinct_colours(shot))
                print(f"screenshot: {time.monotonic() - started:.0f} s: {counts[-1]} colours",
                      file=sys.stderr, flush=True)
                recent = counts[-settle:]
                steady = len(recent) == settle and max(recent) <= 1.25 * min(recent)
                done = drawn(shot) if drawn is not None else steady and min(recent) >= min_colours
                if done or time.monotonic() >= deadline:
                    return shot
        finally:
            tools.close()


INSTALL_HINT = "apt-get install -y --no-install-recommends chromium-headless-shell"


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("url", nargs="?")
    parser.add_argument("output", type=Path, nargs="?")
    parser.add_argument("--check", action="store_true",
                        help="only print the browser that would be used (exit 3: none)")
    parser.add_argument("--browser", help="Chromium executable (default: search PATH)")
    parser.add_argument("--size", default="1280x800", help="window WIDTHxHEIGHT")
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds to wait at most")
    parser.add_argument("--every", type=float, default=3.0, help="seconds between captures")
    parser.add_argument("--min-colours", type=int, default=200,
                        help="a capture with fewer colours is still loading")
    parser.add_argument("--browser-log", type=Path, help="write the browser's own output here")
    args = parser.parse_args(argv)
    browser = find_browser(args.browser)
    if browser is None:
        print(f"screenshot: no Chromium found; install one with '{INSTALL_HINT}' "
              "or name it with --browser / $SWANKY_CHROMIUM", file=sys.stderr)
        return NO_BROWSER
    if args.check:
        print(browser)
        return 0
    if args.url is None or args.output is None:
        parser.error("URL and OUTPUT are required")
    width, height = (int(v) for v in args.size.lower().split("x"))
    with open(args.browser_log or os.devnull, "wb") as log:
        png = capture(args.url, browser=browser, size=(width, height), timeout=args.timeout,
                      every=args.every, min_colours=args.min_colours, log=log)
    args.output.write_bytes(png)
    print(f"{args.output}: {distinct_colours(png)} colours", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
