"""The viewer page in headless Chromium: serve a ViewerData, load the page, return its screenshot and reports."""
from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

from trisplat.viewer.data import ViewerData
from trisplat.viewer.server import ViewerServer

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome")
CHROMIUM_FLAGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-component-update",
    "--disable-sync", "--no-first-run", "--hide-scrollbars", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
    "--force-device-scale-factor=1", "--enable-logging=stderr", "--v=0", "--virtual-time-budget=15000",
]


def find_chromium() -> str | None:
    return next((p for n in CHROMIUM_NAMES if (p := shutil.which(n))), None)


def screenshot(data: ViewerData, query: str, size: tuple[int, int], timeout_s: float = 120.0,
               ready_timeout_s: float = 30.0) -> tuple[np.ndarray, list[dict], str]:
    """(uint8 [H,W,3] screenshot, the page's reports, Chromium's stderr) of the viewer page `?query` in a
    `size` = (width, height) window. Raises FileNotFoundError without Chromium, RuntimeError without a screenshot."""
    from PIL import Image

    chromium = find_chromium()
    if chromium is None:
        raise FileNotFoundError(f"no Chromium on PATH ({', '.join(CHROMIUM_NAMES)}): apt-get install chromium")
    server = ViewerServer(data, port=0)
    server.start_background()
    try:
        with tempfile.TemporaryDirectory(prefix="trisplat-chromium-") as tmp:
            shot = Path(tmp) / "shot.png"
            try:
                proc = subprocess.run(
                    [chromium, *CHROMIUM_FLAGS, f"--user-data-dir={tmp}/profile",
                     f"--window-size={size[0]},{size[1]}", f"--screenshot={shot}", server.url + "?hold=1&" + query],
                    capture_output=True, text=True, timeout=timeout_s)
            except subprocess.TimeoutExpired as exc:
                raise RuntimeError(f"the viewer page did not report ready within {timeout_s:g} s (the screenshot "
                                   f"waits for it); its reports: {server.reports[-5:]}") from exc
            if not shot.is_file():
                raise RuntimeError(f"chromium wrote no screenshot (rc {proc.returncode}): {proc.stderr[-2000:]}")
            image = np.asarray(Image.open(shot).convert("RGB"))
        server.wait_for_report("ready", ready_timeout_s)
    finally:
        server.shutdown()
        server.server_close()
    return image, list(server.reports), proc.stderr
