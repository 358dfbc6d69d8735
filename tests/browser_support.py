"""Helpers of the browser tests (the `chromium` fixture is in tests/conftest.py)."""

from __future__ import annotations

import io
import json
import os
from pathlib import Path
from urllib.parse import urlsplit


def requested_urls(driver) -> list[str]:
    """Every URL the current page requested: Chromium's network log (drained by the call) and the page's own
    resource timing entries."""
    urls = driver.execute_script(
        "return [location.href, ...performance.getEntriesByType('resource').map((e) => e.name)]"
    )
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            urls.append(message["params"]["request"]["url"])
    return urls


def external(urls: list[str]) -> list[str]:
    """The URLs that are neither on a loopback address nor data: URLs."""
    return [
        u
        for u in urls
        if not (u.startswith("data:") or urlsplit(u).hostname in ("127.0.0.1", "localhost", "::1"))
    ]


def save_screenshot(driver, name: str, tmp_path) -> None:
    """A PNG of the page in `tmp_path`; also in $GMT_SCREENSHOT_DIR when set, in 256 colours (how docs/ui-*.png
    are made)."""
    png = driver.get_screenshot_as_png()
    assert png.startswith(b"\x89PNG")
    Path(tmp_path, name).write_bytes(png)
    folder = os.environ.get("GMT_SCREENSHOT_DIR")
    if folder:
        from PIL import Image

        image = Image.open(io.BytesIO(png)).convert("RGB").quantize(256)
        image.save(Path(folder, name), optimize=True)
