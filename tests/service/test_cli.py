"""The `gmt` entry point: a checkpoint it cannot load ends the command with a one-line error, not a traceback."""

import subprocess
import sys
from pathlib import Path

import pytest

GMT = str(Path(sys.executable).parent / "gmt")


@pytest.mark.parametrize(
    ("files", "named"),
    [
        ({"gmt.json": "{}"}, "model.safetensors"),
        ({"gmt.json": "not json", "model.safetensors": ""}, "valid JSON"),
    ],
)
def test_an_unloadable_checkpoint_is_a_one_line_error(tmp_path, files, named):
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    r = subprocess.run([GMT, "eval", str(tmp_path), "--seeds", "1"], capture_output=True, text=True)
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and named in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
