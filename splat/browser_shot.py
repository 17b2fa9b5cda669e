"""A web page as headless Chromium draws it, WebGL in software (SwiftShader): for `splat view
--screenshot` and the viewer's tests.

Chromium's own ``--screenshot`` takes the picture after a budget of *virtual* time, which a page fed
over a websocket and drawn by a slow software renderer overruns or undershoots by minutes. Here the
page is driven over the DevTools protocol instead: load it, wait (real time) until its text shows
``wait_for_text`` (the viewer's last GUI element, so every scene message has arrived), hide the
notification toasts, capture every second until three pictures in a row are the same.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import re
import shutil
import signal
import subprocess
import tempfile
import time
import urllib.request
from pathlib import Path

import numpy as np

from geocues.atomic import atomic_path

log = logging.getLogger(__name__)

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--use-gl=angle", "--use-angle=swiftshader",
                  "--enable-unsafe-swiftshader", "--hide-scrollbars", "--no-first-run", "--mute-audio",
                  "--disable-dev-shm-usage", "--disable-background-networking", "--disable-extensions")
_HIDE_TOASTS = ("document.querySelectorAll('.mantine-Notifications-root, .mantine-Notification-root')"
                ".forEach(e => e.style.display = 'none'); true")


def find_chromium() -> str | None:
    """Path of a Chromium (or Chrome) executable on PATH, or None."""
    for name in CHROMIUM_NAMES:
        path = shutil.which(name)
        if path:
            return path
    return None


class _Page:
    """A minimal DevTools-protocol client of one page target (websockets' sync client)."""

    def __init__(self, ws_url: str):
        from websockets.sync.client import connect

        self.ws = connect(ws_url, max_size=None, open_timeout=30)
        self.next_id = 0

    def call(self, method: str, timeout: float = 60.0, **params):
        self.next_id += 1
        self.ws.send(json.dumps({"id": self.next_id, "method": method, "params": params}))
        deadline = time.monotonic() + timeout
        while True:
            msg = json.loads(self.ws.recv(timeout=max(deadline - time.monotonic(), 0.01)))
            if msg.get("id") == self.next_id:  # events and other replies are skipped
                if "error" in msg:
                    raise RuntimeError(f"DevTools {method}: {msg['error']}")
                return msg.get("result", {})

    def evaluate(self, expression: str):
        return self.call("Runtime.evaluate", expression=expression, returnByValue=True)["result"].get("value")


def _devtools_port(proc: subprocess.Popen, timeout: float) -> int:
    """Chromium prints 'DevTools listening on ws://HOST:PORT/...' on stderr once it is up."""
    deadline = time.monotonic() + timeout
    seen = []
    while time.monotonic() < deadline:
        line = proc.stderr.readline()
        if not line:
            if proc.poll() is not None:
                break
            continue
        seen.append(line)
        m = re.search(r"DevTools listening on ws://[^:]+:(\d+)/", line)
        if m:
            return int(m.group(1))
    raise RuntimeError(f"Chromium gave no DevTools port (exit {proc.poll()}): {''.join(seen)[-2000:]}")


def _until_still(page: _Page, deadline: float, poll_s: float = 1.0, tol: float = 0.05,
                 still: int = 2) -> tuple[bytes, int]:
    """Capture every ``poll_s`` until ``still`` pairs in a row differ by under ``tol`` grey levels on
    average (a software renderer takes seconds to upload, sort and draw 100k splats; a drawn frame
    repeats exactly), or until ``deadline`` (then the last one). Returns (PNG bytes, captures)."""
    import imageio.v3 as iio

    prev, n, run = None, 0, 0
    while True:
        page.evaluate(_HIDE_TOASTS)
        data = base64.b64decode(page.call("Page.captureScreenshot", timeout=max(deadline - time.monotonic(), 30.0),
                                          format="png")["data"])
        img = iio.imread(data).astype(np.float32)
        diff = np.abs(img - prev).mean() if prev is not None and prev.shape == img.shape else np.inf
        log.debug("capture %d: mean %.2f, change %.3f", n, img.mean(), diff)
        n += 1
        run = run + 1 if diff < tol else 0
        if run >= still:
            return data, n
        if time.monotonic() > deadline:
            log.warning("the page still changed after the time limit; saving the last picture")
            return data, n
        prev = img
        time.sleep(poll_s)


def screenshot(url: str, png: str | Path, *, width: int = 1280, height: int = 720,
               wait_for_text: str | None = None, settle_s: float = 2.0, timeout_s: float = 180.0) -> Path:
    """Load ``url`` in headless Chromium and save what it draws as ``png`` (``width`` x ``height``).

    Waits until the page's text contains ``wait_for_text`` (if given; RuntimeError after ``timeout_s``),
    then ``settle_s`` seconds, then until the picture stops changing (:func:`_until_still`).
    FileNotFoundError when no Chromium is installed."""
    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError(f"no Chromium found (looked for {', '.join(CHROMIUM_NAMES)} on PATH); "
                                "on Debian: apt-get install chromium")
    png = Path(png)
    png.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="indoorgs-chromium-") as tmpdir:
        # the profile and the browser's scratch folders (TMPDIR/org.chromium.Chromium.*, which it
        # leaves behind when it is ended) both live in one temporary folder, removed afterwards;
        # unless that path is too long for the unix socket Chromium makes there (108 bytes)
        profile, scratch = Path(tmpdir) / "profile", Path(tmpdir) / "t"
        scratch.mkdir()
        env = dict(os.environ)
        if len(os.fsencode(scratch / "org.chromium.Chromium.XXXXXX/SingletonSocket")) < 108:
            env["TMPDIR"] = str(scratch)
        # own session: the browser's helper processes are ended with it, by its group id
        proc = subprocess.Popen([exe, *CHROMIUM_FLAGS, f"--window-size={width},{height}",
                                 "--remote-debugging-port=0", f"--user-data-dir={profile}", "about:blank"], env=env,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, start_new_session=True)
        try:
            port = _devtools_port(proc, timeout=60.0)
            with urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=30) as r:
                targets = [t for t in json.load(r) if t.get("type") == "page"]
            page = _Page(targets[0]["webSocketDebuggerUrl"])
            page.call("Emulation.setDeviceMetricsOverride", width=width, height=height,
                      deviceScaleFactor=1, mobile=False)
            page.call("Page.navigate", url=url)
            if wait_for_text is not None:
                probe = f"!!document.body && document.body.innerText.includes({json.dumps(wait_for_text)})"
                while not page.evaluate(probe):
                    if time.monotonic() - t0 > timeout_s:
                        raise RuntimeError(f"{url} did not show {wait_for_text!r} within {timeout_s:.0f} s")
                    time.sleep(0.5)
            time.sleep(settle_s)
            data, n = _until_still(page, t0 + timeout_s)
            with atomic_path(png) as tmp:
                tmp.write_bytes(data)
            page.ws.close()
        finally:
            try:
                os.killpg(proc.pid, signal.SIGTERM)
                proc.wait(timeout=10)
            except (ProcessLookupError, subprocess.TimeoutExpired):
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10)
                except ProcessLookupError:
                    pass
            if proc.stderr is not None:
                proc.stderr.close()
    log.info("screenshot of %s after %.1f s (%d captures): %s", url, time.monotonic() - t0, n, png)
    return png
