"""The README's quickstart (curl, Python) and docs/serving.md's walkthrough (curl, httpx, gRPC) run verbatim
against a server, ports aside; the README's facts (make variables, shipped models, the pasted observation) hold."""

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

ROOT = Path(__file__).resolve().parents[2]
README = ROOT / "README.md"
SERVING = ROOT / "docs" / "serving.md"


def blocks(lang: str, text: str) -> list[str]:
    return re.findall(rf"```{lang}\n(.*?)```", text, flags=re.S)


def quickstart() -> str:
    text = README.read_text()
    section = text[text.index("## Quickstart") :]
    return section[: section.index("\n## ", 1)]


def serving_blocks(lang: str) -> list[str]:
    return blocks(lang, SERVING.read_text())


@pytest.fixture(scope="module")
def cheetah_server(tmp_path_factory):
    """A server whose one model is called halfcheetah-gmt (tiny random weights, HalfCheetah-v5 shapes; its goals
    are low, medium, high)."""
    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / "halfcheetah-gmt", name="halfcheetah-gmt")
    s = RunningServer(make_settings(checkpoints=[root])).start()
    yield s
    s.stop()


def localize(code: str, server) -> str:
    return code.replace("localhost:8000", server.url.removeprefix("http://")).replace(
        "localhost:50051", server.target
    )


def run_bash(code: str, server) -> str:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}  # python3 = this venv
    out = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", localize(code, server)],
        capture_output=True,
        text=True,
        env=env,
        timeout=60,
    )
    assert out.returncode == 0, out.stderr
    return out.stdout


def json_documents(text: str) -> tuple[list, str]:
    """The JSON documents printed back to back (curl -s prints bodies without newlines), and what follows."""
    docs, rest, dec = [], text, json.JSONDecoder()
    while rest.lstrip().startswith("{"):
        doc, end = dec.raw_decode(rest.lstrip())
        docs.append(doc)
        rest = rest.lstrip()[end:]
    return docs, rest


# ----- the README's quickstart --------------------------------------------------------------------------------
def test_the_first_curl_comes_early():
    lines = README.read_text().splitlines()
    first = next(i for i, line in enumerate(lines, 1) if line.startswith("curl "))
    assert first <= 60, first
    assert len(lines) <= 300, len(lines)


@pytest.mark.skipif(
    shutil.which("curl") is None or shutil.which("jq") is None, reason="curl and jq are needed"
)
def test_quickstart_curl(cheetah_server):
    (block,) = [b for b in blocks("bash", quickstart()) if "curl" in b and "SID=" in b]
    assert "-H 'Content-Type: application/json'" in block and "example_observation" in block
    docs, rest = json_documents(run_bash(block, cheetah_server))
    goals = [d for d in docs if set(d) == {"id", "name", "mean"}]
    assert [g["name"] for g in goals] == ["low", "medium", "high"]
    acts = [d for d in docs if "action" in d]
    assert [(a["step"], a["goal"], len(a["action"])) for a in acts] == [(0, 0, 6), (1, 2, 6)]
    (state,) = [d for d in docs if "goal_name" in d]
    assert (state["goal_name"], state["step"]) == ("high", 1)
    assert rest.strip() == "204"
    assert cheetah_server.run(cheetah_server.core.store.count()) == 0


def test_quickstart_python(cheetah_server, capsys):
    pytest.importorskip("mujoco")
    (code,) = blocks("python", quickstart())
    exec(compile(localize(code, cheetah_server), "README.md", "exec"), {})
    out = capsys.readouterr().out.splitlines()
    assert [line.split(" x velocity")[0] for line in out] == [
        "step 99 goal 0",
        "step 199 goal 0",
        "step 299 goal 2",  # "high" from step 200
        "step 399 goal 2",
    ]
    assert cheetah_server.run(cheetah_server.core.store.count()) == 0  # the session closed on exit


def test_quickstart_python_prints_what_the_readme_shows_with_the_shipped_model(capsys):
    """The README's printed velocities are the shipped checkpoint's (they went stale once when it was retrained)."""
    pytest.importorskip("mujoco")
    shipped = Path(__file__).resolve().parents[2] / "checkpoints" / "halfcheetah-gmt"
    server = RunningServer(make_settings(checkpoints=[shipped])).start()
    try:
        (code,) = blocks("python", quickstart())
        exec(compile(localize(code, server), "README.md", "exec"), {})
    finally:
        server.stop()
    printed = capsys.readouterr().out.strip()
    shown = re.search(r"```\n(step 99 .*?)```", quickstart(), flags=re.S).group(1).strip()
    assert printed == shown


def test_the_pasted_observation_is_the_example_one():
    pytest.importorskip("mujoco")
    from gmt.service.examples import _first_observation

    pasted = re.search(r"Or paste it:\s*`(\[[^`]*\])`", quickstart()).group(1)
    assert json.loads(pasted) == _first_observation("HalfCheetah-v5", (17,), 0)


def test_the_documented_make_variables_and_targets_exist():
    makefile = (ROOT / "Makefile").read_text()
    text = README.read_text()
    for var in set(re.findall(r"\bmake \w+ ((?:[A-Z_]+=\S+ ?)+)", text)) | {"TRANSPORT=grpc"}:
        for name in re.findall(r"([A-Z_]+)=", var):
            assert re.search(rf"^{name} \?=", makefile, re.M), name
    for target in re.findall(r"^make (\w[\w-]*)", "\n".join(blocks("bash", text)), re.M):
        assert re.search(rf"^{target}:", makefile, re.M), target
    assert "TRANSPORT must be rest or grpc" in makefile


def test_the_model_table_names_the_shipped_checkpoints():
    rows = [line for line in README.read_text().splitlines() if line.startswith("| `") and "-gmt`" in line]
    named = {}
    for row in rows:
        names, envs, goals = (c.strip() for c in row.strip("|").split("|"))
        env_ids = re.findall(r"[\w/]+-v\d+", envs)
        for name, env in zip(re.findall(r"`([\w-]+)`", names), env_ids, strict=True):
            named[name] = (env, goals.split(" (")[0].split(", "))
    shipped = {p.parent.name: json.loads(p.read_text()) for p in ROOT.glob("checkpoints/*/gmt.json")}
    assert set(named) == set(shipped)
    for name, (env, goal_names) in named.items():
        meta = shipped[name]
        assert env == meta["env"]["env_id"], name
        assert goal_names == [g["name"] for g in meta["goals"]], name


# ----- docs/serving.md ----------------------------------------------------------------------------------------
@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_curl_walkthrough(cheetah_server):
    (walkthrough,) = [b for b in serving_blocks("bash") if "curl" in b and "SID=" in b]
    docs, rest = json_documents(run_bash(walkthrough, cheetah_server))
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
    out = run_bash(block, cheetah_server)
    doc, end = json.JSONDecoder().raw_decode(out)
    assert out[end:].strip() == ""  # the DELETEs answer 204 with no body
    ok, bad = doc["results"]
    assert (ok["step"], ok["goal"], len(ok["action"])) == (0, 0, 6)
    assert bad["session_id"] != ok["session_id"] and set(bad) == {"session_id", "error"}
    assert bad["error"]["code"] == "invalid_argument"
    assert bad["error"]["message"].startswith("observation has 2 values, expected 17")
    assert cheetah_server.run(cheetah_server.core.store.count()) == 0  # the block closed its sessions


def test_python_snippets(cheetah_server, capsys):
    code_blocks = serving_blocks("python")
    assert len(code_blocks) == 2
    for code in code_blocks:
        exec(compile(localize(code, cheetah_server), "docs/serving.md", "exec"), {})
    out = capsys.readouterr().out
    assert "9 2 [" in out  # httpx: step 9 acts on the highest goal
    assert out.count("act act {") == 2 and "session session {" in out  # the Control stream answered in order
    r = cheetah_server.run(cheetah_server.core.store.count())
    assert r == 0  # both snippets closed their sessions
