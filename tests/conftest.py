"""Shared fixtures: tiny random-weight checkpoints built in milliseconds."""

import json
import shutil
import subprocess
import sys

import pytest
import torch

from gmt.model.fixtures import tiny_checkpoint


@pytest.fixture(autouse=True, scope="session")
def _threads():
    torch.set_num_threads(1)


@pytest.fixture
def tiny_ckpt_dir(tmp_path):
    """A saved tiny HalfCheetah-v5 checkpoint directory (3 goals, K = 5)."""
    d = tmp_path / "checkpoints" / "tiny-gmt"
    tiny_checkpoint(d)
    return d


@pytest.fixture
def imports_of():
    """imports_of("a", "b.c") -> the packages a fresh interpreter has loaded after importing them: top-level
    names, and this project's as `gmt.<package>` (e.g. {"numpy", "gmt", "gmt.client"})."""

    def run(*modules: str) -> set[str]:
        names = "{'.'.join(m.split('.')[: 2 if m.startswith('gmt.') else 1]) for m in sys.modules}"
        code = f"import json, sys\nimport {', '.join(modules)}\nprint(json.dumps(sorted({names})))"
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
        return set(json.loads(out))

    return run


@pytest.fixture(scope="session")
def chromium():
    """A headless Chromium: the system's (Debian `chromium`, `chromium-driver`) through Selenium, which is given
    both paths so that it downloads nothing. Its performance log records every request a page makes
    (`browser_support.external_requests`)."""
    webdriver = pytest.importorskip("selenium.webdriver")
    from selenium.webdriver.chrome.service import Service

    browser, driver = shutil.which("chromium"), shutil.which("chromedriver")
    if browser is None or driver is None:
        pytest.skip("needs the system Chromium and its driver (apt-get install chromium chromium-driver)")
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in (
        "--headless=new",
        "--no-sandbox",  # as root in a container
        "--disable-dev-shm-usage",
        "--disable-gpu",
        "--window-size=1100,860",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-default-apps",
        "--disable-sync",
    ):
        options.add_argument(arg)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    d = webdriver.Chrome(service=Service(driver), options=options)
    d.set_page_load_timeout(60)
    d.set_script_timeout(60)
    yield d
    d.quit()
