"""The `gmt` console command: every registered command answers --help, options come from the configurations they
fill (same defaults), the command lines written in the repository (Makefile, README, docs/, PROVENANCE.md) still
parse, and the entry point is lazy."""

from __future__ import annotations

import dataclasses
import json
import re
import shlex
import subprocess
import sys
from importlib import metadata
from pathlib import Path

import pytest
from typer.main import get_command
from typer.testing import CliRunner

from gmt.common.extras import missing
from gmt.service.cli import COMMANDS, app

ROOT = Path(__file__).resolve().parents[1]
runner = CliRunner()


def _gmt() -> str:
    return str(Path(sys.executable).parent / "gmt")


def _root():
    return get_command(app)


def _every_command() -> list[tuple[str, ...]]:
    """The path of every registered command and sub-command, read from the CLI itself."""
    root, paths = _root(), []
    ctx = root.make_context("gmt", ["--help"], resilient_parsing=True)
    for name in root.list_commands(ctx):
        cmd = root.get_command(ctx, name)
        paths.append((name,))
        real = getattr(cmd, "real", cmd)
        if hasattr(real, "list_commands"):
            paths += [(name, sub) for sub in real.list_commands(ctx)]
    return paths


def test_help_lists_every_registered_command():
    out = subprocess.run([_gmt(), "--help"], capture_output=True, text=True, check=True).stdout
    paths = _every_command()
    assert {p[0] for p in paths} >= {e.name for e in COMMANDS} | {"version"}
    for name, *_rest in paths:
        assert re.search(rf"│ {name}\s", out), name


@pytest.mark.parametrize("path", _every_command(), ids=" ".join)
def test_every_command_answers_help(path):
    r = runner.invoke(app, [*path, "--help"])
    assert r.exit_code == 0, r.output
    assert "Usage: gmt " + " ".join(path) in " ".join(r.output.split())


def test_listed_help_is_the_commands_own_first_line():
    for entry in COMMANDS:
        if entry.extra and missing(entry.extra):
            continue
        real = entry.load()
        assert (real.help or "").split("\n\n")[0].replace("\n", " ").strip() == entry.help, entry.name


def test_version_prints_the_installed_versions():
    out = subprocess.run([_gmt(), "version"], capture_output=True, text=True, check=True).stdout
    assert f"torch {metadata.version('torch')}" in out
    assert "extra serve: installed" in out


def test_entry_point_imports_no_command_module(imports_of):
    assert not imports_of("gmt.service.cli") & {
        "torch",
        "numpy",
        "gmt.model",
        "pydantic_settings",
        "grpc",
        "gymnasium",
    }


# ----- options generated from the configuration -----------------------------------------------------------------
def _params(path: str) -> dict:
    entry = next(e for e in COMMANDS if e.name == path)
    return {p.name: p for p in entry.load().params}


@pytest.mark.parametrize(
    "command, config, skipped",
    [
        ("train", "gmt.model.config:TrainConfig", {"extra"}),
        ("train", "gmt.model.config:GMTConfig", {"obs_shape", "act_dim", "discrete_actions", "n_goals"}),
        ("run", "gmt.client.runner:RunConfig", {"transport", "schedule", "random_schedule", "goal"}),
    ],
)
def test_every_flag_default_is_the_config_default(command, config, skipped):
    module, _, name = config.partition(":")
    cls = getattr(__import__(module, fromlist=[name]), name)
    params = _params(command)
    for f in dataclasses.fields(cls):
        if f.name in skipped:
            continue
        assert f.name in params, f"{cls.__name__}.{f.name} has no flag"
        assert params[f.name].default == f.default, (f.name, params[f.name].default, f.default)
        assert params[f.name].help, f"{cls.__name__}.{f.name} has no help (document it under Attributes:)"
    if command == "run":
        assert params["goal"].default == str(cls.goal)


def test_every_serve_flag_shows_the_settings_default():
    from gmt.service.settings import TUNING, Settings

    params = _params("serve")
    assert TUNING <= set(Settings.model_fields) and not TUNING & set(params)  # tuning knobs: environment only
    for name, info in Settings.model_fields.items():
        if name in TUNING:
            continue
        p = params[name]
        assert p.default is None, name  # an unset flag leaves GMT_<NAME> (or the default) in force
        assert f"GMT_{name.upper()}" in p.help and len(p.help) > len(f"[GMT_{name.upper()}]")
        if name == "replica_id":
            continue  # computed per process
        default = info.get_default(call_default_factory=True)
        if default is None:
            assert p.show_default is True, name
        else:
            shown = ", ".join(map(str, default)) if isinstance(default, list) else str(default)
            assert p.show_default == shown, name


# ----- the command lines written in the repository still parse ---------------------------------------------------
def _written_command_lines() -> list[tuple[str, str]]:
    texts = [("Makefile", (ROOT / "Makefile").read_text()), ("README.md", (ROOT / "README.md").read_text())]
    texts += [(str(p.relative_to(ROOT)), p.read_text()) for p in sorted(ROOT.glob("docs/*.md"))]
    texts += [(str(p.relative_to(ROOT)), p.read_text()) for p in ROOT.glob("checkpoints/*/PROVENANCE.md")]
    for p in ROOT.glob("checkpoints/*/gmt.json"):
        texts.append((str(p.relative_to(ROOT)), json.loads(p.read_text()).get("command", "")))
    make_vars = dict(re.findall(r"^(\w+) \??:?= *(.*)$", texts[0][1], re.M))
    lines = []
    for where, text in texts:
        text = re.sub(r"\\\n\s*", " ", text)
        for line in text.splitlines():
            m = re.match(
                r"^\s*(?:\$\(BIN\)/|\.venv/bin/)?(gmt (?:train|eval|serve|run|data \w+|cluster \w+|bench)\b[^#&|;`]*)",
                line,
            )
            if m and "..." not in m.group(1):  # a line that elides its arguments is not a command to run
                line = m.group(1)
                for _ in range(10):  # nested variables, e.g. $(DEMO_VIA_$(TRANSPORT)), inner first
                    line = re.sub(r"\$\((\w+)\)", lambda v: make_vars.get(v.group(1), v.group(1)), line)
                lines.append((where, line.strip()))
    return lines


def test_the_written_command_lines_find_commands():
    wheres = {w for w, _ in _written_command_lines()}
    assert {"Makefile", "README.md", "docs/training.md", "docs/data.md", "docs/clients.md"} <= wheres
    assert any(w.endswith("PROVENANCE.md") for w in wheres)


@pytest.mark.parametrize("where, line", _written_command_lines(), ids=lambda x: x[:60])
def test_written_command_line_parses(where, line):
    args = shlex.split(line)[1:]
    entry = next(e for e in COMMANDS if e.name == args[0])
    if entry.extra and missing(entry.extra):
        pytest.skip(f"the {entry.extra} extra is not installed")
    cmd, args = entry.load(), args[1:]
    if hasattr(cmd, "list_commands"):
        cmd, args = cmd.get_command(None, args[0]), args[1:]
    if "--" in args:  # `gmt cluster up ... -- more gmt serve flags`
        args = args[: args.index("--")]
    cmd.make_context(entry.name, args)  # raises on an unknown option or a bad value


# A checkpoint `gmt` cannot load ends the command with a one-line error, not a traceback.
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
    r = subprocess.run(
        [str(Path(sys.executable).parent / "gmt"), "eval", str(tmp_path), "--seeds", "1"],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 1
    assert r.stderr.startswith("error: ") and named in r.stderr, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr


# The user's mistakes (a path that is not there or of the wrong kind, an unknown environment, flags that cannot
# work) end the command with a one-line error, before any long work, not a traceback.
@pytest.mark.parametrize(
    ("args", "status", "named"),
    [
        (["data", "describe", "gmt/nosuch/mixed-v0"], 1, "gmt data collect"),
        (["data", "collect", "--env", "halfcheetah-v5", "--out-id", "gmt/x/y-v0"], 1, "Did you mean"),
        (["eval", "{tmp}/nope"], 1, "does not exist"),
        (["bench", "--sections", "bogus"], 2, "choose among"),  # was exit 0 with no figure
        (["eval", "checkpoints/halfcheetah-gmt", "--seeds", "0"], 2, "--seeds"),
        (["eval", "checkpoints/halfcheetah-gmt", "--threads", "0"], 2, "--threads"),
        (["eval", "checkpoints/halfcheetah-gmt", "--json", "{tmp}"], 2, "is a directory"),
        (["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o", "--steps", "0"], 2, "steps"),
        (["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o", "--n-head", "3"], 2, "n_head=3"),
        (["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o", "--k", "1"], 2, "k must be >= 2"),
        (
            ["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o", "--statistic", "x"],
            2,
            "unknown statistic",
        ),
        (
            ["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o", "--labels", "{tmp}/l.json"],
            2,
            "not a file",
        ),
        (["train", "--dataset", "gmt/nosuch/x-v0", "--out", "{tmp}/o"], 1, "gmt data collect"),
    ],
)
def test_a_users_mistake_is_a_short_error_without_a_traceback(tmp_path, args, status, named):
    argv = [a.replace("{tmp}", str(tmp_path)) for a in args]
    env = {**__import__("os").environ, "GMT_DATA_DIR": str(tmp_path / "data"), "COLUMNS": "200"}
    r = subprocess.run([_gmt(), *argv], capture_output=True, text=True, cwd=ROOT, env=env, timeout=120)
    assert r.returncode == status, (r.returncode, r.stderr[-2000:])
    assert named in r.stderr and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert not (tmp_path / "o").exists()  # nothing was written


def test_planning_from_rest_a_level_without_a_plan_is_refused_before_collecting(tmp_path):
    r = runner.invoke(
        app,
        ["data", "collect", "--env", "Hopper-v5", "--data-dir", str(tmp_path), "--plan", "slow=1.0,1.3",
         "--plan-from-rest", "fast"],
    )  # fmt: skip
    assert r.exit_code == 2
    assert "--plan-from-rest" in r.output and "['fast'] have no --plan" in r.output, r.output
    assert not any(tmp_path.iterdir())
    r = runner.invoke(
        app,
        ["data", "collect", "--env", "Hopper-v5", "--data-dir", str(tmp_path), "--plan", "slow=1.0,1.3",
         "--plan-from-rest", "slow=fast"],
    )  # fmt: skip
    assert r.exit_code == 2 and "LEVEL=SPEED" in r.output, r.output


@pytest.mark.parametrize(
    "item, message",
    [("fast=1.2", "['fast'] have no --plan"), ("slow=quick", "LEVEL=SPEED"), ("slow=nan", "LEVEL=SPEED"),
     ("slow", "LEVEL=SPEED")],
)  # fmt: skip
def test_a_bad_plan_target_is_refused_before_collecting(tmp_path, item, message):
    r = runner.invoke(
        app,
        ["data", "collect", "--env", "Hopper-v5", "--data-dir", str(tmp_path), "--plan", "slow=1.0,1.3",
         "--plan-target", item],
    )  # fmt: skip
    assert r.exit_code == 2
    assert "--plan-target" in r.output and message in r.output, r.output
    assert not any(tmp_path.iterdir())


def test_a_plan_target_reaches_only_its_levels_plan(tmp_path, monkeypatch):
    import gmt.datagen.collect as collect_module

    seen = []
    monkeypatch.setattr(collect_module, "collect", lambda cfg: seen.append(cfg) or _raise_exit())
    r = runner.invoke(
        app,
        ["data", "collect", "--env", "Hopper-v5", "--data-dir", str(tmp_path), "--plan", "slow=1.0,1.3",
         "--plan", "fast=2.0", "--plan-target", "slow=0.95", "--plan-from-rest", "slow=1.1",
         "--plan-rest-commands", "slow=3.6,1.6"],
    )  # fmt: skip
    assert r.exit_code == 0, r.output
    (cfg,) = seen
    assert cfg.plan["slow"].target == 0.95 and cfg.plan["slow"].for_rest().target == 1.1
    assert cfg.plan["slow"].commands == (1.0, 1.3) and cfg.plan["slow"].for_rest().commands == (3.6, 1.6)
    assert cfg.plan["fast"].target is None and cfg.plan["fast"].rest_commands is None


@pytest.mark.parametrize(
    "item, message",
    [("fast=3.0", "'fast' has no --plan-from-rest"), ("slow=quick", "LEVEL=COMMAND"), ("slow", "LEVEL=COMMAND")],
)  # fmt: skip
def test_bad_rest_commands_are_refused_before_collecting(tmp_path, item, message):
    r = runner.invoke(
        app,
        ["data", "collect", "--env", "Hopper-v5", "--data-dir", str(tmp_path), "--plan", "slow=1.0,1.3",
         "--plan", "fast=2.0", "--plan-from-rest", "slow", "--plan-rest-commands", item],
    )  # fmt: skip
    assert r.exit_code == 2
    assert "--plan-rest-commands" in r.output and message in r.output, r.output
    assert not any(tmp_path.iterdir())


def _raise_exit():
    import typer

    raise typer.Exit(0)


def test_the_behaviour_folders_the_written_command_lines_collect_from_exist():
    dirs = [
        (where, m.group(1))
        for where, line in _written_command_lines()
        for m in [re.search(r"--behaviour-dir (\S+)", line)]
        if m and not m.group(1).startswith("runs/")
    ]
    assert dirs, "no --behaviour-dir in the Makefile or a PROVENANCE.md"
    for where, d in dirs:
        assert any((ROOT / d).glob("*/*.safetensors")), f"{where}: {d} holds no behaviour snapshot"


def _written_checkpoint_args(flag: str, *skip: str) -> list[tuple[str, str, str]]:
    """(where, path, line) of every written command line with `flag PATH`, PATH not under a `skip` prefix."""
    return [
        (where, m.group(1), line)
        for where, line in _written_command_lines()
        if (m := re.search(rf"{flag} (\S+)", line)) and not m.group(1).startswith(skip)
    ]


def test_the_pool_checkpoints_the_written_command_lines_start_from_exist_for_their_environment():
    """A written collection that starts episodes from a GMT's states names a committed checkpoint of its task."""
    from gmt.model.checkpoint import load_checkpoint

    pools = [
        (where, path, re.search(r"--env (\S+)", line).group(1))
        for where, path, line in _written_checkpoint_args("--pool-checkpoint", "runs/")
    ]
    remake = "checkpoints/hopper-gmt/PROVENANCE.md"
    assert any(where == remake for where, _, _ in pools), f"no --pool-checkpoint in {remake}"
    for where, path, env_id in pools:
        assert (ROOT / path / "gmt.json").is_file(), f"{where}: {path} is not a checkpoint"
        assert load_checkpoint(ROOT / path).env_id == env_id, f"{where}: {path} is not a {env_id} model"


def test_the_checkpoints_written_trainings_start_from_are_committed_models_of_one_shape():
    """A written `gmt train --init-from` names a committed checkpoint (a device run's copy under .devdata/ or a
    scratch one under runs/ aside) whose model configuration the trained checkpoint shares."""
    from gmt.model.checkpoint import load_checkpoint

    inits = [
        (where, path, o.group(1) if (o := re.search(r"--out (\S+)", line)) else None)
        for where, path, line in _written_checkpoint_args("--init-from", "runs/", ".devdata/")
    ]
    remake = "checkpoints/breakout-dagger-gmt/PROVENANCE.md"
    assert any(where == remake for where, _, _ in inits), f"no --init-from in {remake}"
    for where, path, out in inits:
        assert (ROOT / path / "gmt.json").is_file(), f"{where}: {path} is not a checkpoint"
        if out and (ROOT / out / "gmt.json").is_file():
            a, b = load_checkpoint(ROOT / path).model.cfg, load_checkpoint(ROOT / out).model.cfg
            assert a == b, f"{where}: {out} is not the shape of {path}"
