"""No answer redirects to the Host header: Starlette's trailing-slash redirects (`/models/` -> 307 to
`http://<Host>/models`) built their Location from it, an open redirect for anyone who can set Host (a proxy
forwarding it, a poisoned cache). They are off; a path with a slash too many is a 404."""

from __future__ import annotations

from urllib.parse import urlsplit

import pytest

EVIL = "evil.example"
PATHS = [
    ("GET", "/healthz/"),
    ("GET", "/readyz/"),
    ("GET", "/metrics/"),
    ("GET", "/models/"),
    ("GET", "/models/tiny-gmt/"),
    ("POST", "/sessions/"),
    ("GET", "/sessions/abc/"),
    ("DELETE", "/sessions/abc/"),
    ("POST", "/sessions/abc/act/"),
    ("POST", "/act/"),
    ("PUT", "/sessions/abc/goal/"),
    ("POST", "/sessions/abc/reset/"),
    ("GET", "/docs/"),
    ("GET", "/redoc/"),
    ("GET", "/openapi.json/"),
    ("GET", "/docs/oauth2-redirect/"),
    ("GET", "/"),
]


@pytest.mark.parametrize("method,path", PATHS, ids=[f"{m} {p}" for m, p in PATHS])
def test_no_redirect_reflects_the_host_header(http, method, path):
    headers = {"Host": EVIL, "X-Forwarded-Host": EVIL, "X-Forwarded-Proto": "https"}
    r = http.request(method, path, headers=headers, json={} if method in ("POST", "PUT") else None)
    location = r.headers.get("location")
    assert location is None or (EVIL not in location and not urlsplit(location).netloc), (
        r.status_code,
        location,
    )
    assert not 300 <= r.status_code < 400, (r.status_code, location)
    if path.endswith("/") and path != "/":
        assert r.status_code == 404 and r.json()["error"]["code"] == "not_found"


def test_the_documented_paths_still_answer_with_a_foreign_host(http):
    r = http.get("/models", headers={"Host": EVIL})
    assert r.status_code == 200 and "tiny-gmt" in {m["name"] for m in r.json()["models"]}
