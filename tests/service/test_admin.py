"""`gmt.service.admin`: which `Host` values name this machine, and the tokenless rule's refusals of web pages."""

from __future__ import annotations

import pytest
from service_harness import make_settings

from gmt.service import admin
from gmt.service.errors import PermissionDenied


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("localhost", True),
        ("LOCALHOST:8000", True),
        ("console.localhost:8000", True),  # RFC 6761: never resolved through DNS
        ("127.0.0.1:8000", True),
        ("127.3.4.5", True),
        ("[::1]:8000", True),
        ("localhost.attacker.example", False),
        ("127.0.0.1.nip.io", False),
        ("attacker.example:8000", False),
        ("10.0.0.1", False),
        ("localhost:port", False),
        ("", False),
        ("[::1", False),
    ],
)
def test_loopback_names(host, loopback):
    assert admin.is_loopback_name(host) is loopback


def test_a_tokenless_call_from_this_machine_is_checked_for_web_pages(tmp_path):
    s = make_settings(checkpoints=[tmp_path])
    ok = {"host": "127.0.0.1:8000"}
    admin.authorize(s, None, "127.0.0.1", False, web=ok)
    admin.authorize(s, None, "127.0.0.1", False, web={**ok, "origin": "http://127.0.0.1:8000"})
    admin.authorize(s, None, "::1", False)  # gRPC: no browser speaks it
    for web in (
        {},
        {"host": "a.example"},
        {**ok, "origin": "null"},
        {**ok, "referer": "http://127.0.0.1:9000/"},
    ):
        with pytest.raises(PermissionDenied):
            admin.authorize(s, None, "127.0.0.1", False, web=web)
    admin.authorize(
        make_settings(checkpoints=[tmp_path], admin_token="t"),
        "Bearer t",
        "203.0.113.9",
        True,
        web={"host": "x"},
    )
