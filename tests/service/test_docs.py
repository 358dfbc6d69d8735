"""`/docs` and `/redoc` work offline: their assets come from this server, and a browser that can reach nothing but
loopback renders them (headless Chromium, network blocked). Auth on, they stay open."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
from urllib.parse import urlsplit

import httpx
import pytest

from service.rest import docs

CHROMIUM = next((p for p in map(shutil.which, ("chromium", "chromium-browser")) if p), None)
URL = re.compile(r"""https?://[^\s"'<>)]+""")
TOKEN = "docs-token"


@pytest.fixture(scope="module")
def guarded(ckpt_root):
    """A server with auth on (the docs must not need the token)."""
    from service_harness import RunningServer, make_settings

    s = RunningServer(make_settings(checkpoints=[ckpt_root], auth_token=TOKEN)).start()
    yield s
    s.stop()


@pytest.mark.parametrize("page", ["/docs", "/redoc"])
def test_docs_pages_name_no_other_host_and_their_assets_are_served(guarded, page):
    with httpx.Client(base_url=guarded.url, timeout=30) as http:
        r = http.get(page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html")
        assert URL.findall(r.text) == []  # no CDN, no fonts, no favicon elsewhere
        assets = re.findall(r'(?:src|href)="([^"]+)"', r.text)
        assert assets and all(a.startswith(docs.ASSETS + "/") for a in assets)
        for a in assets:  # without a token
            got = http.get(a)
            assert got.status_code == 200 and got.headers["content-type"].startswith(
                docs.FILES[a.split("/")[-1]]
            )
            assert len(got.content) > 1000
        assert http.get("/openapi.json").status_code == 200
        assert http.get("/docs/oauth2-redirect").status_code == 200
        assert http.get("/models").status_code == 401  # the API itself still needs it
        assert http.get(f"{docs.ASSETS}/nope.js").status_code == 401  # only the assets are open


def test_the_served_redoc_bundle_names_no_image_on_another_host(guarded):
    body = httpx.get(f"{guarded.url}{docs.ASSETS}/redoc.standalone.js", timeout=30).content
    assert docs.REDOCLY_LOGO in (docs.STATIC / "redoc.standalone.js").read_bytes()  # the package's has one
    assert docs.REDOCLY_LOGO not in body and b"data:," in body


def _offline_chromium(url: str, tmp_path) -> tuple[str, list[tuple[str, str]]]:
    """The DOM of `url` after its scripts ran in headless Chromium that reaches loopback only, and the
    (initiator, url) of every request the page made."""
    netlog = tmp_path / "netlog.json"
    cmd = [
        CHROMIUM,
        "--headless",
        "--disable-gpu",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        # Network blocked but for loopback: no name resolves, and everything else goes to a proxy that refuses
        # (Chromium never sends loopback through a proxy).
        "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
        "--proxy-server=http://127.0.0.1:9",
        f"--log-net-log={netlog}",
        "--virtual-time-budget=20000",  # run the page's scripts and fetches, then dump
        "--dump-dom",
        url,
    ]
    if os.geteuid() == 0:
        cmd.insert(1, "--no-sandbox")  # Chromium refuses to run as root with its sandbox
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    log = json.loads(netlog.read_text())
    start = log["constants"]["logEventTypes"]["URL_REQUEST_START_JOB"]
    origin = f"{urlsplit(url).scheme}://{urlsplit(url).netloc}"
    requests = [
        (e["params"].get("initiator", ""), e["params"]["url"])
        for e in log["events"]
        if e["type"] == start and "url" in e.get("params", {})
    ]
    by_page = [(i, u) for i, u in requests if i == origin or u.startswith(origin)]  # not Chromium's own
    return out.stdout, by_page


def _loopback(url: str) -> bool:
    return urlsplit(url).hostname in ("127.0.0.1", "localhost", "::1")


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_swagger_ui_renders_the_operations_offline(guarded, tmp_path):
    dom, requests = _offline_chromium(f"{guarded.url}/docs", tmp_path)
    assert 'class="swagger-ui"' in dom
    paths = set(re.findall(r'class="opblock-summary-path" data-path="([^"]+)"', dom))
    assert {"/sessions", "/sessions/{session_id}/act", "/act", "/models/{name}"} <= paths
    assert f"{guarded.url}/openapi.json" in {u for _, u in requests}
    assert [u for _, u in requests if not _loopback(u)] == []


@pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium)")
def test_redoc_renders_the_operations_offline(guarded, tmp_path):
    dom, requests = _offline_chromium(f"{guarded.url}/redoc", tmp_path)
    assert "redoc-wrap" in dom and "/sessions/{session_id}/act" in dom
    assert f"{guarded.url}/openapi.json" in {u for _, u in requests}
    assert [u for _, u in requests if not _loopback(u)] == []
