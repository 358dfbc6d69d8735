"""docs/models.md as a user follows it, from outside: `gmt models copy` makes a second version, the `gmt models`
block loads, promotes and drains (as written, `GMT_SERVER` pointed at a `gmt serve` on free ports in a copy of the
checkpoint folder), and after a restart `gmt models list` shows the promoted default."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

from service_harness import ServeProcess, run_doc_block

ROOT = Path(__file__).resolve().parents[2]
MODELS_MD = ROOT / "docs" / "models.md"
SHIPPED = ROOT / "checkpoints" / "halfcheetah-gmt"


def section_block(title: str) -> str:
    text = MODELS_MD.read_text()
    section = text[text.index(f"## {title}") :]
    return re.findall(r"```bash\n(.*?)```", section, flags=re.S)[0]


def test_models_md_rollout_survives_a_restart(tmp_path):
    (tmp_path / "checkpoints" / "halfcheetah-gmt").mkdir(parents=True)
    for f in ("gmt.json", "model.safetensors"):
        shutil.copyfile(SHIPPED / f, tmp_path / "checkpoints" / "halfcheetah-gmt" / f)
    copy = run_doc_block(section_block("A second version to roll out"), tmp_path)
    assert (
        copy.returncode == 0 and "wrote checkpoints/releases/halfcheetah-gmt-v2 (version v2" in copy.stdout
    ), copy

    first = ServeProcess(cwd=tmp_path)
    try:
        serving = first.wait_serving()
        assert serving["model_state"] == "file checkpoints/gmt-models.json" and serving[
            "recording"
        ].startswith("off")
        script = section_block("With `gmt models`").replace("http://127.0.0.1:8000", first.url)
        out = run_doc_block(script, tmp_path)
        assert out.returncode == 0, out.stdout + out.stderr
        assert f"server {first.url} (--server or GMT_SERVER)" in out.stderr
        assert (
            f"promoting halfcheetah-gmt v2 to the default on {first.url} (default was ac667fb5665b)"
            in out.stderr
        )
        assert "draining halfcheetah-gmt ac667fb5665b (0 session(s))" in out.stderr
    finally:
        first.proc.terminate()
        first.proc.wait(60)

    again = ServeProcess(cwd=tmp_path)
    try:
        again.wait_serving()
        out = run_doc_block(f"gmt models list --server {again.url}", tmp_path)
        rows = [line.split() for line in out.stdout.splitlines()[1:-1]]
        assert ["halfcheetah-gmt", "v2", "serving", "0", "default"] in rows, out.stdout
        assert out.stdout.splitlines()[-1].startswith("defaults and canaries are kept across restarts")
    finally:
        again.kill()
