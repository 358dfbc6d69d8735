"""The thin client: the clients import neither torch nor `model/`, and the base install alone (`pip install .`, no
extra) drives a session of a running server over REST and gRPC with `clients/examples/remote_session.py`."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import venv
from pathlib import Path

import pytest

from gmt.common.extras import distributions

ROOT = Path(__file__).resolve().parents[2]
HEAVY = ("torch", "scikit-learn", "minari", "stable-baselines3", "safetensors", "mujoco", "matplotlib")


def test_clients_import_neither_torch_nor_model(imports_of):
    loaded = imports_of(
        "gmt.client.rest",
        "gmt.client.grpc",
        "gmt.client.runner",
        "gmt.client.envs",
        "gmt.client.segments",
        "gmt.client.cli",
    )
    assert "torch" not in loaded and "gmt.model" not in loaded
    assert not loaded & {"sklearn", "minari", "safetensors", "stable_baselines3", "mujoco", "matplotlib"}


def test_the_base_install_declares_nothing_heavy():
    base = set(distributions(""))
    assert base and not base & set(HEAVY), base & set(HEAVY)
    assert {"torch", "safetensors"} <= set(distributions("serve"))


@pytest.fixture(scope="module")
def thin_venv(tmp_path_factory) -> Path:
    """A fresh virtual environment with the project installed from a wheel, no extra, at constraints.txt."""
    tmp = tmp_path_factory.mktemp("thin")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for name in ("clients", "common", "model", "service", "proto"):
        shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(
        [*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp / "wheel"), str(src)], check=True
    )
    env_dir = tmp / "venv"
    venv.create(env_dir, with_pip=True)
    wheel = next((tmp / "wheel").glob("gmt_service-*.whl"))
    thin_pip = [str(env_dir / "bin" / "python"), "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(
        [*thin_pip, "install", "-c", str(ROOT / "constraints.txt"), str(wheel)], check=True, timeout=600
    )
    return env_dir


def test_thin_install_has_no_training_or_data_stack(thin_venv):
    out = subprocess.run(
        [str(thin_venv / "bin" / "python"), "-m", "pip", "list", "--format", "json"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    names = {p["name"].lower().replace("_", "-") for p in json.loads(out)}
    assert "gmt-service" in names and {"grpcio", "httpx", "numpy", "protobuf"} <= names
    assert not names & set(HEAVY), names & set(HEAVY)


def test_thin_install_drives_a_session_over_rest_and_grpc(thin_venv, live_server, tmp_path):
    script = ROOT / "clients" / "examples" / "remote_session.py"
    r = subprocess.run(
        [
            str(thin_venv / "bin" / "python"),
            str(script),
            "--rest",
            live_server.rest_url,
            "--grpc",
            live_server.grpc_target,
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,  # the installed package, not the source tree
        timeout=120,
    )
    assert r.returncode == 0, r.stdout + r.stderr
    assert "rest: 20 actions" in r.stdout and "grpc: 20 actions" in r.stdout
    assert "rest and grpc answered the same actions" in r.stdout


def test_thin_gmt_names_the_extra_a_command_needs(thin_venv, live_server, tmp_path):
    gmt = str(thin_venv / "bin" / "gmt")
    assert subprocess.run([gmt, "--help"], capture_output=True, text=True, cwd=tmp_path).returncode == 0
    r = subprocess.run([gmt, "serve", "--rest-port", "0"], capture_output=True, text=True, cwd=tmp_path)
    assert (
        r.returncode == 1 and "pip install 'gmt-service[serve]'" in r.stderr and "Traceback" not in r.stderr
    )
    r = subprocess.run(
        [gmt, "train", "--dataset", "d", "--out", "o"], capture_output=True, text=True, cwd=tmp_path
    )
    assert r.returncode == 1 and "pip install 'gmt-service[train]'" in r.stderr
    # gmt run works in the base install; a MuJoCo environment asks for the `run` extra.
    r = subprocess.run(
        [gmt, "run", "--server", live_server.rest_url, "--steps", "3"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert r.returncode == 1 and "pip install 'gmt-service[run]'" in r.stderr, r.stdout + r.stderr
