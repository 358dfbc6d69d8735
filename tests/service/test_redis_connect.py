"""Store URLs: the sentinel form is parsed exactly, every malformed URL is a startup error naming the problem (and
never the password), and the settings that need a Redis store say so."""

import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from pydantic import ValidationError

from gmt.service.redis_connect import SentinelURL, parse_redis_url, redacted
from gmt.service.settings import Settings


@pytest.mark.parametrize(
    ("url", "want"),
    [
        ("redis://127.0.0.1:6379/0", None),
        ("rediss://:pw@cache.example:6380/2", None),
        ("unix:///run/redis.sock?db=1", None),
        (
            "redis+sentinel://127.0.0.1:26379,127.0.0.1:26380,127.0.0.1:26381/gmt",
            SentinelURL((("127.0.0.1", 26379), ("127.0.0.1", 26380), ("127.0.0.1", 26381)), "gmt"),
        ),
        (
            "redis+sentinel://:p%40ss@s1,[::1]:5000/my-primary/3",
            SentinelURL((("s1", 26379), ("::1", 5000)), "my-primary", 3, None, "p@ss"),
        ),
        ("REDIS+SENTINEL://app:pw@s1:1/gmt", SentinelURL((("s1", 1),), "gmt", 0, "app", "pw")),
    ],
)
def test_accepted_urls(url, want):
    got = parse_redis_url(url)
    assert got == want
    if want is not None:
        assert got.password == want.password  # not compared by ==: kept out of repr


@pytest.mark.parametrize(
    ("url", "message"),
    [
        (
            "redis+sentinal://s1:26379/gmt",
            "must start with redis://, rediss://, unix:// or redis+sentinel://",
        ),
        ("localhost:6379", "must start with"),
        ("redis://h:99999/0", "Port out of range"),
        ("redis+sentinel://s1:26379", "names no service"),
        ("redis+sentinel://s1:26379/", "names no service"),
        ("redis+sentinel:///gmt", "names no sentinel"),
        ("redis+sentinel://s1:0/gmt", "port '0' of 's1:0' is not a number in 1..65535"),
        ("redis+sentinel://s1:x/gmt", "port 'x'"),
        ("redis+sentinel://s1:1,,s2:2/gmt", "'' is not host[:port]"),
        ("redis+sentinel://s1:1,s1:1/gmt", "names a sentinel twice"),
        ("redis+sentinel://s1:1/gmt/zero", "only a database number may follow"),
        ("redis+sentinel://s1:1/gmt/0/1", "only a database number may follow"),
        ("redis+sentinel://s1:1/g%20mt", "may hold only letters"),
        ("redis+sentinel://s1:1/gmt?socket_timeout=1", "takes no ?options"),
        ("redis+sentinel://secret@s1:1/gmt", "write the password as ':password@'"),
    ],
)
def test_malformed_urls_name_the_problem(url, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        parse_redis_url(url)


def test_settings_check_the_url_and_the_replicas_setting():
    with pytest.raises(ValidationError, match="names no service"):
        Settings(redis_url="redis+sentinel://127.0.0.1:26379")
    with pytest.raises(ValidationError, match="store_min_replicas needs a Redis store"):
        Settings(store_min_replicas=1)
    with pytest.raises(ValidationError, match="store_wait_timeout_s"):
        Settings(redis_url="redis://127.0.0.1:6379/0", store_wait_timeout_s=0)
    s = Settings(redis_url="redis+sentinel://127.0.0.1:26379/gmt", store_min_replicas=1)
    assert (s.store_min_replicas, s.store_wait_timeout_s) == (1, 1.0)


def test_redacted_hides_only_the_password():
    assert redacted("redis+sentinel://:s3cret@a:1,b:2/gmt") == "redis+sentinel://:***@a:1,b:2/gmt"
    assert redacted("redis://app:s3cret@h:6379/0") == "redis://app:***@h:6379/0"
    assert redacted("redis://h:6379/0") == "redis://h:6379/0"


def test_gmt_serve_refuses_a_bad_url_at_startup_without_showing_the_password():
    gmt = str(Path(sys.executable).parent / "gmt")
    bad = "redis+sentinel://:s3cret@127.0.0.1:26379,127.0.0.1:26379/gmt"
    env = {**os.environ, "COLUMNS": "400"}  # one line per message in typer's error box
    r = subprocess.run(
        [gmt, "serve", "--redis-url", bad], capture_output=True, text=True, timeout=60, env=env
    )
    assert r.returncode == 2, r.stderr
    assert "redis_url: Value error, sentinel URL 'redis+sentinel://:***@127.0.0.1:26379" in r.stderr
    assert "names a sentinel twice" in r.stderr
    assert "s3cret" not in r.stderr + r.stdout


def test_gmt_serve_exits_with_a_clear_message_when_no_sentinel_names_a_primary(tmp_path):
    gmt = str(Path(sys.executable).parent / "gmt")
    ports = []
    for _ in range(2):
        with socket.socket() as s:  # nothing listens there once closed
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    url = f"redis+sentinel://127.0.0.1:{ports[0]},127.0.0.1:{ports[1]}/gmt"
    args = [gmt, "serve", "--redis-url", url, "--rest-port", "0", "--grpc-port", "0", "-c", str(tmp_path)]
    r = subprocess.run(args, capture_output=True, text=True, timeout=60)
    assert r.returncode == 1, r.stderr
    assert "error: session store unreachable: No master found for 'gmt'" in r.stderr
    assert "Traceback" not in r.stderr
