"""The README's serving walkthrough (curl, httpx, gRPC) runs verbatim against a server, ports aside."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from service_harness import RunningServer, make_settings

from gmt.model.fixtures import tiny_checkpoint

README = Path(__file__).resolve().parents[2] / "README.md"


def serving_blocks(lang: str) -> list[str]:
    text = README.read_text()
    section = text[text.index("## Serving") :]
    section = section[: section.index("\n## ", 1)]
    return re.findall(rf"```{lang}\n(.*?)```", section, flags=re.S)


@pytest.fixture(scope="module")
def cheetah_server(tmp_path_factory):
    """A server whose one model is called halfcheetah-gmt (tiny random weights, HalfCheetah-v5 shapes)."""
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / "halfcheetah-gmt", name="halfcheetah-gmt")
    s = RunningServer(make_settings(checkpoints=[root])).start()
    yield s
    s.stop()


def localize(code: str, server) -> str:
    return code.replace("localhost:8000", server.url.removeprefix("http://")).replace(
        "localhost:50051", server.target
    )


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_curl_walkthrough(cheetah_server):
    (walkthrough,) = [b for b in serving_blocks("bash") if "curl" in b and "SID=" in b]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}  # python3 = this venv
    out = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", localize(walkthrough, cheetah_server)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    docs, rest, dec = [], out.stdout, json.JSONDecoder()
    while rest.lstrip().startswith("{"):  # curl -s prints bodies back to back, without newlines
        doc, end = dec.raw_decode(rest.lstrip())
        docs.append(doc)
        rest = rest.lstrip()[end:]
    assert docs[0]["models"][0]["name"] == "halfcheetah-gmt"
    acts = [d for d in docs if "action" in d]
    assert [(a["step"], a["goal"], len(a["action"])) for a in acts] == [(0, 0, 6), (1, 2, 6)]
    goals = [d for d in docs if "blend_remaining" in d]
    assert (goals[0]["goal"], goals[0]["blend_remaining"]) == (2, 20)  # the highest goal, blended
    assert goals[1]["goal"] == 0  # target 0.5 -> nearest mean 0.0 of the tiny model's goals 0, 1, 2
    assert rest.strip() == "204"


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_curl_many_sessions_in_one_call(cheetah_server):
    (block,) = [b for b in serving_blocks("bash") if "localhost:8000/act " in b]
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}  # python3 = this venv
    out = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", localize(block, cheetah_server)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    doc, end = json.JSONDecoder().raw_decode(out.stdout)
    assert out.stdout[end:].strip() == ""  # the DELETEs answer 204 with no body
    ok, bad = doc["results"]
    assert (ok["step"], ok["goal"], len(ok["action"])) == (0, 0, 6)
    assert bad["session_id"] != ok["session_id"] and set(bad) == {"session_id", "error"}
    assert bad["error"]["code"] == "invalid_argument"
    assert bad["error"]["message"].startswith("observation has 2 values, expected 17")
    assert cheetah_server.run(cheetah_server.core.store.count()) == 0  # the block closed its sessions


def test_python_snippets(cheetah_server, capsys):
    blocks = serving_blocks("python")
    assert len(blocks) == 2
    for code in blocks:
        exec(compile(localize(code, cheetah_server), "README.md", "exec"), {})
    out = capsys.readouterr().out
    assert "9 2 [" in out  # httpx: step 9 acts on the highest goal
    assert out.count("act act {") == 2 and "session session {" in out  # the Control stream answered in order
    r = cheetah_server.run(cheetah_server.core.store.count())
    assert r == 0  # both snippets closed their sessions
