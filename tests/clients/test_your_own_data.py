"""docs/your-own-data.md's worked example, run as written: a user's CartPole policy collected at two levels, goals
from a statistic of the user's choosing (`mean(abs(obs[2]))`), a small model trained, evaluated, served (here
in-process, on loopback) and driven by `gmt run`: the two goals give different statistics in the model's default
action mode, which training chose because the goals do nothing in `expert`."""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "your-own-data.md"


def example() -> tuple[str, list[list[str]]]:
    """The worked example's policy file and its `gmt` command lines, in order."""
    text = DOC.read_text().split("## Worked example", 1)[1]
    blocks = re.findall(r"```(\w+)\n(.*?)```", text, flags=re.S)
    policy = next(body for lang, body in blocks if lang == "python" and body.startswith("# my_cartpole.py"))
    commands = []
    for lang, body in blocks:
        if lang == "bash":
            commands += [shlex.split(line) for line in body.replace("\\\n", " ").splitlines() if line.strip()]
    return policy, commands


def test_the_docs_example_serves_goals_that_control_a_custom_statistic_of_a_discrete_environment(
    tmp_path, start_server
):
    policy, commands = example()
    assert [c[:2] for c in commands] == [["gmt", "data"]] * 2 + [["gmt", "train"], ["gmt", "eval"], ["gmt", "serve"]] + [["gmt", "run"]] * 2  # fmt: skip
    (tmp_path / "my_cartpole.py").write_text(policy)
    env = {**os.environ, "GMT_DATA_DIR": str(tmp_path / "data"), "OMP_NUM_THREADS": "1", "COLUMNS": "200"}
    gmt = str(Path(sys.executable).parent / "gmt")
    out = {}
    server = None
    for cmd in commands:
        if cmd[1] == "serve":  # the server, in this process on a free loopback port
            server = start_server(tmp_path / cmd[cmd.index("--checkpoints") + 1])
            continue
        if cmd[1] == "run":
            cmd = [*cmd, "--server", server.rest_url]
        r = subprocess.run(
            [gmt, *cmd[1:]], cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300
        )
        assert r.returncode == 0, f"{shlex.join(cmd)}\n{r.stdout}\n{r.stderr}"
        out[" ".join(cmd[:2])] = r.stdout
    assert "statistic: mean(abs(obs[2]))" in out["gmt data"]  # describe: the user's statistic clustered
    meta = json.loads((tmp_path / "checkpoints/cartpole-wobble/gmt.json").read_text())
    assert meta["statistic"] == "mean(abs(obs[2]))" and meta["default_action_mode"] == "sample"
    spread = meta["goal_spread"]["total_variation"]
    assert spread["expert"] < 0.02 <= spread["sample"]  # why sample: expert would leave the goals alike
    assert "sessions default to sample" in out["gmt train"]
    assert "action mode sample" in out["gmt eval"]
    achieved = {}
    for goal in ("low", "high"):
        docs = [json.loads(p.read_text()) for p in sorted((tmp_path / "runs" / goal).glob("episode-*.json"))]
        assert len(docs) == 2 and all(d["statistic"] == "mean(abs(obs[2]))" for d in docs)
        achieved[goal] = float(np.mean([s["achieved"] for d in docs for s in d["segments"]]))
    goals = {g["name"]: g["mean"] for g in meta["goals"]}
    assert achieved["high"] > 3 * achieved["low"], achieved  # the goals control the statistic
    assert abs(achieved["low"] - goals["low"]) < abs(achieved["low"] - goals["high"])
    assert abs(achieved["high"] - goals["high"]) < abs(achieved["high"] - goals["low"])
