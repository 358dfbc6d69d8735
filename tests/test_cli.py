"""The `gmt` console command is installed and lists its command groups."""

import shutil
import subprocess
import sys
from pathlib import Path


def _gmt() -> list[str]:
    exe = Path(sys.executable).parent / "gmt"
    return [str(exe)] if exe.exists() else [shutil.which("gmt") or "gmt"]


def test_help_lists_commands():
    out = subprocess.run([*_gmt(), "--help"], capture_output=True, text=True, check=True).stdout
    assert "version" in out


def test_version_prints_torch():
    out = subprocess.run([*_gmt(), "version"], capture_output=True, text=True, check=True).stdout
    assert "torch 2.13.0" in out
