"""The printed outputs the README and docs/ show are what their commands print today: each output block preceded by

    <!-- docs-test output: COMMAND | within TOL -->

is produced again by running COMMAND (a shell line; `python-above` runs the doc's preceding ```python block) against
one server with the shipped halfcheetah-gmt on free ports (`$REST_PORT`, `$GRPC_PORT`; `localhost:8000` in a
Python block), and each of the block's lines must appear, in order, among the lines printed: words equal, numbers
within TOL. Outputs go under a temporary folder (`runs/` in a command is rewritten there, and back in what it
prints). A stale number in a doc fails here. Blocks too long for CI are marked as such (`LONG_MARKER`)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from service_harness import RunningServer, clean_env, make_settings

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
VENV = Path(sys.prefix)
MARKER = re.compile(r"<!-- docs-test output: (.*?) \| within ([0-9.]+) -->\n```[a-z]*\n(.*?)```", re.S)
NUMBER = re.compile(r"[-+]?\d+\.\d+")
LONG_MARKER = "<!-- docs-test: long, not run in CI (its gmt lines are parsed by tests/test_cli.py) -->"
# A block that a test of its own runs as written (a short version of a long command: your-own-data.md's example).
RUN_MARKER = "<!-- docs-test: run as written by tests/clients/test_your_own_data.py -->"
# Commands too long for CI: collecting data, training, full evaluations, benchmarks.
LONG = re.compile(
    r"(^|\s|/)(gmt (train|eval|bench|data (collect|gait|commanded|plan|refine|ppo|dagger))|make (train|eval|data|bench)[\w-]*)\b"
)


def marked() -> list[tuple[Path, str, float, str, str]]:
    """(doc, command, tolerance, expected output, the doc's text before the marker) of every marked block."""
    found = []
    for doc in DOCS:
        text = doc.read_text()
        for m in MARKER.finditer(text):
            found.append((doc, m.group(1), float(m.group(2)), m.group(3), text[: m.start()]))
    return found


def matches(want: str, got: str, tol: float) -> bool:
    """Whether line `got` is line `want` with every decimal number within `tol`."""
    if NUMBER.sub("#", want).split() != NUMBER.sub("#", got).split():
        return False
    return all(
        abs(float(a) - float(b)) <= tol
        for a, b in zip(NUMBER.findall(want), NUMBER.findall(got), strict=True)
    )


def compare(expected: str, printed: str, tol: float) -> list[str]:
    """The expected lines not found, in order, among the printed ones."""
    lines, missing, i = printed.splitlines(), [], 0
    for want in (w for w in expected.splitlines() if w.strip()):
        j = next((k for k in range(i, len(lines)) if matches(want, lines[k], tol)), None)
        if j is None:
            missing.append(want)
        else:
            i = j + 1
    return missing


@pytest.fixture(scope="module")
def cheetah():
    """The shipped halfcheetah-gmt on free loopback ports, shared by every marked block."""
    s = RunningServer(make_settings(checkpoints=[ROOT / "checkpoints" / "halfcheetah-gmt"])).start()
    yield s
    s.stop()


BLOCKS = marked()


def test_the_markers_are_found():
    docs = {doc.name for doc, *_ in BLOCKS}
    assert {"README.md", "clients.md"} <= docs, docs
    assert compare("a 1.20 b\nc 2.00", "x\na 1.21 b\ny\nc 1.99\n", 0.02) == []
    assert compare("a 1.20 b", "a 1.25 b", 0.02) == ["a 1.20 b"]


def test_every_long_block_is_marked_as_not_run():
    """A shell block that collects data, trains, evaluates in full or benchmarks says so right above it (its command
    lines are still parsed, flags included, by tests/test_cli.py), unless a test of its own runs it as written."""
    unmarked = []
    for doc in DOCS:
        text = doc.read_text()
        for m in re.finditer(r"```bash\n(.*?)```", text, flags=re.S):
            above = text[: m.start()].rstrip("\n")
            if LONG.search(m.group(1)) and not above.endswith((LONG_MARKER, RUN_MARKER)):
                unmarked.append(f"{doc.name}:{text[: m.start()].count(chr(10)) + 1}")
    assert not unmarked, f"long blocks without {LONG_MARKER}: {unmarked}"


@pytest.mark.skipif(shutil.which("make") is None, reason="make is not installed")
@pytest.mark.parametrize("block", BLOCKS, ids=lambda b: f"{b[0].name}:{b[1][:40]}")
def test_a_documented_output_is_what_its_command_prints(cheetah, block, tmp_path):
    doc, command, tol, expected, before = block
    rest, grpc = str(cheetah.server.rest_port), str(cheetah.server.grpc_port)
    env = clean_env(
        PATH=f"{VENV / 'bin'}{os.pathsep}{os.environ['PATH']}",
        OMP_NUM_THREADS="1",
        COLUMNS="200",
        TERM="dumb",
    )
    if command == "python-above":
        code = re.findall(r"```python\n(.*?)```", before, flags=re.S)[-1]
        cmd = [sys.executable, "-c", code.replace("localhost:8000", f"localhost:{rest}")]
    else:
        line = (
            command.replace("$REST_PORT", rest)
            .replace("$GRPC_PORT", grpc)
            .replace("runs/", f"{tmp_path}/runs/")
        )
        if line.startswith("make "):  # the run extra is installed here: -o skips make's pip install
            line = f"make --no-print-directory -o {VENV}/.installed-run VENV={VENV} " + line[len("make ") :]
        cmd = ["bash", "-euo", "pipefail", "-c", line]
    out = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, env=env, timeout=300)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    printed = out.stdout.replace(f"{tmp_path}/runs/", "runs/")
    missing = compare(expected, printed, tol)
    assert not missing, (
        f"{doc.name}: stale output (numbers within {tol}):\n"
        + "\n".join(missing)
        + (f"\n--- printed ---\n{printed[-3000:]}")
    )
