"""Every ```bash block of the README and docs/ is accounted for by the comment line right above it:

    <!-- docs-test: run by tests/service/test_doc_blocks.py -->   run here (below), as written
    <!-- docs-test: run by tests/PATH.py -->                        run by that test (it must name the doc)
    <!-- docs-test: long, not run in CI ... -->                     too long for CI (tests/service/test_doc_outputs.py)
    <!-- docs-test: not run: REASON -->                             needs what CI lacks (podman, Kubernetes, a network)

An unmarked block fails. The blocks run here go, in document order, one bash script per doc (so `$S` set in one
block is there in the next), against one server with the shipped halfcheetah-gmt and hopper-gmt on free ports,
recording to `runs/recordings`. Substitutions, the only changes: `localhost:8000` / `127.0.0.1:8000` become the
server's REST address, `localhost:50051` its gRPC one; a line starting `make serve` or `gmt serve` is left out (the
test's server stands in for it); `runs/` is a temporary folder; curl fails on an HTTP error answer (4xx, 5xx).
Every command must succeed, and a ```text block
right after a run block must be among what it printed (numbers within 0.02)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from service_harness import RunningServer, clean_env, make_settings
from test_doc_outputs import compare

ROOT = Path(__file__).resolve().parents[2]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
VENV = Path(sys.prefix)
HERE = "tests/service/test_doc_blocks.py"
MARK = re.compile(
    r"<!-- docs-test: (?:run (?:as written )?by (tests/\S+\.py)|long, not run in CI .*|not run: (.+)) -->$"
)
BLOCK = re.compile(r"```bash\n(.*?)```(?:\n\n```(?:text|console)\n(.*?)```)?", re.S)
SERVER_LINE = re.compile(r"^(make serve|gmt serve|\.venv/bin/gmt serve)\b.*\n?", re.M)


def bash_blocks(doc: Path) -> list[tuple[int, str, str, str | None]]:
    """(line, the comment line above, the block, the ```text block right after it or None) of each bash block."""
    text = doc.read_text()
    out = []
    for m in BLOCK.finditer(text):
        above = text[: m.start()].rstrip("\n").rsplit("\n", 1)[-1]
        out.append((text[: m.start()].count("\n") + 1, above, m.group(1), m.group(2)))
    return out


def to_run() -> dict[str, list[tuple[int, str, str | None]]]:
    """The blocks this test runs, by doc."""
    found: dict[str, list] = {}
    for doc in DOCS:
        for line, above, block, shown in bash_blocks(doc):
            m = MARK.search(above)
            if m and m.group(1) == HERE:
                found.setdefault(doc.name, []).append((line, block, shown))
    return found


def test_every_bash_block_is_run_or_marked_with_a_reason():
    unaccounted, wrong = [], []
    for doc in DOCS:
        for line, above, _, _ in bash_blocks(doc):
            m = MARK.search(above)
            if not m:
                unaccounted.append(f"{doc.name}:{line}")
            elif m.group(1) and m.group(1) != HERE:
                test = ROOT / m.group(1)
                if not test.is_file() or doc.name not in test.read_text():
                    wrong.append(f"{doc.name}:{line} -> {m.group(1)}")
    assert not unaccounted, f"bash blocks neither run nor marked (see {HERE}'s docstring): {unaccounted}"
    assert not wrong, f"blocks said to be run by a test that does not exist or never names the doc: {wrong}"


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    """The shipped halfcheetah-gmt and hopper-gmt on free loopback ports, recording under a temporary runs/."""
    runs = tmp_path_factory.mktemp("docs") / "runs"
    s = RunningServer(
        make_settings(
            checkpoints=[ROOT / "checkpoints" / "halfcheetah-gmt", ROOT / "checkpoints" / "hopper-gmt"],
            record_dir=runs / "recordings",
        )
    ).start()
    yield s, runs
    s.stop()


def localize(block: str, rest: str, grpc: str, runs: Path) -> str:
    block = SERVER_LINE.sub("", block)
    for a, b in (("localhost:8000", rest), ("127.0.0.1:8000", rest), ("localhost:50051", grpc)):
        block = block.replace(a, b)
    return re.sub(r"(?<![\w/.])runs/", f"{runs}/", block)


RUN = to_run()


@pytest.mark.parametrize("doc", sorted(RUN))
def test_the_blocks_run_as_written(server, doc):
    s, runs = server
    rest = f"127.0.0.1:{s.server.rest_port}"
    grpc = f"127.0.0.1:{s.server.grpc_port}"
    env = clean_env(
        PATH=f"{VENV / 'bin'}{os.pathsep}{os.environ['PATH']}",
        OMP_NUM_THREADS="1",
        COLUMNS="200",
        TERM="dumb",
    )
    script = ['curl() { command curl --fail-with-body "$@"; }']  # an HTTP error answer fails the block
    for i, (line, block, _) in enumerate(RUN[doc]):
        script.append(f"echo '@@block {i} ({doc}:{line})'\n{localize(block, rest, grpc, runs)}")
    out = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", "\n".join(script)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert out.returncode == 0, f"{doc}: a block failed\n{out.stdout[-3000:]}\n{out.stderr[-3000:]}"
    printed = out.stdout.replace(f"{runs}/", "runs/")
    parts = re.split(r"^@@block \d+ .*\n", printed, flags=re.M)[1:]
    for (line, _, shown), got in zip(RUN[doc], parts, strict=True):
        if shown is not None:
            missing = compare(shown, got, 0.02)
            assert not missing, (
                f"{doc}:{line}: stale output (numbers within 0.02):\n"
                + "\n".join(missing)
                + f"\n--- printed ---\n{got[-3000:]}"
            )
