"""Installs by role (docs/install.md): what each extra brings, the lock that pins them, what serving imports;
the one import package (`gmt`) an install puts into site-packages, and the base install on every supported Python
(3.11, 3.12, 3.13: each found here is used, the others are skipped) driving a live server."""

from __future__ import annotations

import ast
import glob
import json
import re
import shutil
import subprocess
import sys
import tomllib
import venv
from importlib import import_module
from pathlib import Path

import pytest

from gmt.common.extras import distributions, extras

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
SETUPTOOLS = PYPROJECT["tool"]["setuptools"]
PYTHONS = ("3.11", "3.12", "3.13")
HEAVY = ("torch", "scikit-learn", "minari", "stable-baselines3", "safetensors", "mujoco", "matplotlib")
DATA_AND_TRAINING = {
    "sklearn",
    "minari",
    "h5py",
    "scipy",
    "mujoco",
    "matplotlib",
    "stable_baselines3",
    "tensorboard",
    "gmt.datagen",
}


def _pins() -> dict[str, str]:
    lines = (ROOT / "constraints.txt").read_text().splitlines()
    pins = dict(line.split("==", 1) for line in lines if line and not line.startswith("#"))
    return {re.sub(r"[-_.]+", "-", k).lower(): v for k, v in pins.items()}


def test_constraints_pin_every_distribution_of_every_extra():
    pins = _pins()
    for extra in ["", *extras()]:
        unpinned = [d for d in distributions(extra) if d not in pins]
        assert not unpinned, f"{extra or 'base'}: {unpinned} not in constraints.txt (make constraints)"


def test_the_torch_version_is_written_only_in_the_constraints():
    version = _pins()["torch"].split("+")[0]
    assert version
    for name in ("pyproject.toml", "Makefile", "docker/Dockerfile", ".ci/run"):
        text = (ROOT / name).read_text()
        assert version not in text and not re.search(r"torch\s*[=<>~]=", text), name


def test_serving_imports_nothing_of_the_data_or_training_stack(imports_of):
    loaded = imports_of(
        "gmt.service.server",
        "gmt.service.serve_cli",
        "gmt.service.redis_store",
        "gmt.model.engine",
        "gmt.model.checkpoint",
    )
    assert "torch" in loaded and not loaded & DATA_AND_TRAINING


# ----- one import package ----------------------------------------------------------------------------------------
def _folder(package: str) -> Path:
    """The repository folder of `package` under [tool.setuptools.package-dir] (the longest mapped prefix)."""
    mapped = SETUPTOOLS["package-dir"]
    prefix = max((p for p in mapped if package == p or package.startswith(p + ".")), key=len)
    return ROOT / mapped[prefix] / package[len(prefix) :].lstrip(".").replace(".", "/")


def test_every_package_folder_is_installed_under_gmt():
    listed = set(SETUPTOOLS["packages"])
    assert all(p == "gmt" or p.startswith("gmt.") for p in listed)
    found = set()
    for top, folder in SETUPTOOLS["package-dir"].items():
        for init in (ROOT / folder).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / folder).parts
            found.add(".".join((top, *rel)))
    assert found == listed, (
        f"package folders not listed in pyproject.toml: {found - listed}; gone: {listed - found}"
    )


def test_the_tests_import_this_checkout():
    """The editable install (`make venv`) maps every package onto its folder here, so tests run this code."""
    for package in SETUPTOOLS["packages"]:
        module = import_module(package)
        assert Path(module.__file__).parent == _folder(package), package


def test_nothing_installed_imports_or_points_into_research():
    """research/ is not installed: no module of the package imports it (statically or by name) or sends its reader
    there for what the package does."""
    hits = []
    for folder in {ROOT / f for f in SETUPTOOLS["package-dir"].values()}:
        for path in folder.rglob("*.py"):
            text = path.read_text()
            for node in ast.walk(ast.parse(text)):
                names = []
                if isinstance(node, ast.Import):
                    names = [a.name for a in node.names]
                elif isinstance(node, ast.ImportFrom) and node.level == 0:
                    names = [node.module or ""]
                elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
                    if getattr(node.func, "id", getattr(node.func, "attr", "")) in (
                        "import_module",
                        "__import__",
                    ):
                        names = [str(node.args[0].value)]
                hits += [
                    f"{path.relative_to(ROOT)}: imports {n}" for n in names if n.split(".")[0] == "research"
                ]
            hits += [f"{path.relative_to(ROOT)}: names {m}" for m in re.findall(r"\bresearch[./]\w+", text)]
    assert not hits, hits


def test_the_image_copies_every_folder_the_package_is_built_from():
    copied = set(re.findall(r"^COPY (\S+) \1$", (ROOT / "docker" / "Dockerfile").read_text(), re.M))
    assert copied == {Path(f).parts[0] for f in SETUPTOOLS["package-dir"].values()}


# ----- fresh installs of the wheel, one per Python -----------------------------------------------------------------
def _python(version: str) -> str | None:
    """An interpreter of `version` with venv and pip: this one, else on PATH, else a pyenv version."""
    if f"{sys.version_info.major}.{sys.version_info.minor}" == version:
        return sys.executable
    candidates = [shutil.which(f"python{version}")]
    candidates += sorted(glob.glob(str(Path.home() / f".pyenv/versions/{version}.*/bin/python{version}")))
    for exe in filter(None, candidates):
        r = subprocess.run(
            [exe, "-c", "import sys, venv, ensurepip; print('%d.%d' % sys.version_info[:2])"],
            capture_output=True,
            text=True,
        )
        if r.returncode == 0 and r.stdout.strip() == version:
            return exe
    return None


@pytest.fixture(scope="session")
def wheel(tmp_path_factory) -> Path:
    """The project's wheel, built from the folders pyproject.toml maps (and nothing else of the checkout)."""
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    src.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(ROOT / name, src / name)
    for folder in {Path(f).parts[0] for f in SETUPTOOLS["package-dir"].values()}:
        shutil.copytree(ROOT / folder, src / folder, ignore=shutil.ignore_patterns("__pycache__"))
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "-w", str(tmp), str(src)], check=True)
    return next(tmp.glob("gmt_service-*.whl"))


@pytest.fixture(scope="module", params=PYTHONS)
def thin_venv(request, wheel, tmp_path_factory) -> Path:
    """A fresh virtual environment of one Python with the wheel installed, no extra, at constraints.txt."""
    exe = _python(request.param)
    if exe is None:
        pytest.skip(
            f"no Python {request.param} with venv and pip here (python{request.param}, ~/.pyenv/versions)"
        )
    env_dir = tmp_path_factory.mktemp(f"thin-{request.param}")
    if exe == sys.executable:
        venv.create(env_dir, with_pip=True)
    else:
        subprocess.run([exe, "-m", "venv", str(env_dir)], check=True, timeout=300)
    pip = [str(env_dir / "bin" / "python"), "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(
        [*pip, "install", "-c", str(ROOT / "constraints.txt"), str(wheel)], check=True, timeout=600
    )
    return env_dir


def _run(env_dir: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([str(env_dir / "bin" / "python"), *args], capture_output=True, text=True, cwd=cwd)


def test_an_install_puts_one_import_package_into_site_packages(thin_venv, tmp_path):
    code = (
        "import importlib.metadata as m, importlib.util as u, json, sys, sysconfig, gmt;"
        "d = m.distribution('gmt-service');"
        "print(json.dumps({'files': [str(f) for f in d.files], 'top': d.read_text('top_level.txt').split(),"
        "'gmt': gmt.__file__, 'site': sysconfig.get_paths()['purelib'], 'version': gmt.__version__,"
        "'others': [n for n in ('model', 'service', 'clients') if u.find_spec(n)]}))"
    )
    r = _run(thin_venv, "-c", code, cwd=tmp_path)  # not the repository: the installed package
    assert r.returncode == 0, r.stderr
    info = json.loads(r.stdout)
    entries = {f.split("/")[0] for f in info["files"] if not f.startswith("..")}  # (bin/gmt lies outside)
    assert entries == {"gmt", f"gmt_service-{info['version']}.dist-info"}, entries
    assert info["top"] == ["gmt"] and not info["others"], info
    assert "gmt/cluster/nginx.conf" in info["files"]  # `gmt cluster` renders it: an install runs clusters too
    assert Path(info["gmt"]).parent == Path(info["site"]) / "gmt"
    assert info["version"] == PYPROJECT["project"].get("version", info["version"])


def test_thin_install_has_no_training_or_data_stack(thin_venv, tmp_path):
    r = _run(thin_venv, "-m", "pip", "list", "--format", "json", cwd=tmp_path)
    names = {p["name"].lower().replace("_", "-") for p in json.loads(r.stdout)}
    assert "gmt-service" in names and {"grpcio", "httpx", "numpy", "protobuf"} <= names
    assert not names & set(HEAVY), names & set(HEAVY)


@pytest.fixture(scope="module")
def live_server(tmp_path_factory):
    """A server over a tiny random-weight checkpoint, in this process (REST and gRPC on free loopback ports)."""
    from service_harness import RunningServer, make_settings

    from gmt.model.fixtures import tiny_checkpoint

    root = tmp_path_factory.mktemp("checkpoints")
    tiny_checkpoint(root / "tiny-gmt")
    server = RunningServer(make_settings(checkpoints=[root])).start()
    yield server
    server.stop()


def test_thin_install_drives_a_session_over_rest_and_grpc(thin_venv, live_server, tmp_path):
    script = ROOT / "clients" / "examples" / "remote_session.py"
    r = subprocess.run(
        [
            str(thin_venv / "bin" / "python"),
            str(script),
            "--rest",
            live_server.url,
            "--grpc",
            live_server.target,
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
        [gmt, "run", "--server", live_server.url, "--steps", "3"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
    )
    assert r.returncode == 1 and "pip install 'gmt-service[run]'" in r.stderr, r.stdout + r.stderr
