"""A speed governor: an outer loop that steers a commanded actor's command so its mean speed holds a target.

A speed-commanded actor (`gmt.datagen.train_commanded`) holds its command only on average: measured on Hopper, its
slow gait's speed over 150-step windows wanders by ~0.1 m/s, about the protocol's whole tolerance, and after a
sprint it brakes over ~100 steps. A GMT imitates both. The governor closes the loop that PPO left open: every
step it reads the x-velocity from the observation and sets the actor's command to

    clip(target + kp * (target - mean of the last `window` speeds) + integral, command_range)

where `integral` sums `ki * (target - speed)` each step (held within +-`integral_limit`, and frozen while the
command is clipped, so it does not wind up). The proportional term brakes or pushes harder right after a change
(and depends only on the last `window` observations, which a GMT with a context of at least `window` steps
sees); the integral removes the actor's own bias and slow drift. The actor must have been trained on commands
over the whole `command_range` (`gmt data commanded --command-range`), or a corrected command is one it never
saw.

Research: no shipped dataset uses it. Its snapshots are of kind `governed`, whose loader this module registers,
so they are collected through this module (`python -m research.governor collect ...`; research/README.md).
"""

from __future__ import annotations

import json
import shlex
import sys
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import typer
from safetensors.torch import load_file

from gmt.datagen.behaviour import (
    BEHAVIOUR_DIR,
    BehaviourMeta,
    BehaviourPolicy,
    env_slug,
    load_actor,
    register_kind,
    save_behaviour,
)
from gmt.datagen.cli import parse_range, parse_targets
from gmt.model.data.minari_io import x_velocity_obs_index


@dataclass(frozen=True)
class GovernorConfig:
    """Gains and limits of a `SpeedGovernor`.

    Attributes:
        vx_index: Index of the x-velocity in the environment's observation vector
            (`gmt.model.data.minari_io.x_velocity_obs_index`).
        command_range: (lo, hi): the commands the actor was trained on; every command is clipped into it.
        window: Steps of speed averaged by the proportional term.
        kp: Proportional gain on (target - window mean speed).
        ki: Per-step gain of the integral of (target - speed).
        integral_limit: Bound on the integral term's magnitude (m/s of command).
    """

    vx_index: int
    command_range: tuple[float, float]
    window: int = 20
    kp: float = 1.0
    ki: float = 0.002
    integral_limit: float = 0.5

    def __post_init__(self) -> None:
        lo, hi = self.command_range
        if not lo < hi:
            raise ValueError(f"command_range must be (lo, hi) with lo < hi, got {self.command_range}")
        if self.vx_index < 0:
            raise ValueError(f"vx_index must be >= 0, got {self.vx_index}")
        if self.window < 1:
            raise ValueError(f"window must be >= 1, got {self.window}")
        if self.kp < 0 or self.ki < 0 or self.integral_limit < 0:
            raise ValueError("kp, ki and integral_limit must be >= 0")
        object.__setattr__(self, "command_range", (float(lo), float(hi)))

    def to_json(self) -> dict:
        """The config as JSON-ready values (stored in a behaviour snapshot's `extra["governor"]`)."""
        return {**asdict(self), "command_range": list(self.command_range)}


class SpeedGovernor:
    """The per-episode state of the outer speed loop (`GovernorConfig`); call `reset` at every episode start."""

    def __init__(self, cfg: GovernorConfig, target: float):
        self.cfg = cfg
        self.target = float(target)
        self.speeds: deque[float] = deque(maxlen=cfg.window)
        self.integral = 0.0

    def reset(self) -> None:
        """Forget the speeds and the integral (a new episode)."""
        self.speeds.clear()
        self.integral = 0.0

    def command(self, obs: np.ndarray) -> float:
        """The command for the step about to be taken at observation `obs` (one observation, not a batch)."""
        obs = np.asarray(obs)
        if obs.ndim != 1:
            raise ValueError(f"a governed policy acts on one observation at a time, got shape {obs.shape}")
        c = self.cfg
        speed = float(obs[c.vx_index])
        self.speeds.append(speed)
        lo, hi = c.command_range
        raw = self.target + c.kp * (self.target - float(np.mean(self.speeds))) + self.integral
        command = min(max(raw, lo), hi)
        if command == raw:  # conditional integration: no wind-up while the command is clipped
            self.integral = min(
                max(self.integral + c.ki * (self.target - speed), -c.integral_limit), c.integral_limit
            )
        return command


class GovernedPolicy:
    """A commanded actor whose command a `SpeedGovernor` sets before every action (snapshots of kind `governed`).

    Args:
        actor: The commanded actor; its command is the level's target speed.
        cfg: The governor's gains and limits.
    """

    def __init__(self, actor: BehaviourPolicy, cfg: GovernorConfig):
        if actor.command is None:
            raise ValueError("a governed snapshot needs extra.command (its target speed)")
        self.actor = actor
        self.governor = SpeedGovernor(cfg, actor.command)

    def __getattr__(self, name: str):  # meta, normalise, low, high, ...: the actor's
        return getattr(self.actor, name)

    @property
    def noise_scale(self) -> float:
        """Multiplies the actor's Gaussian noise std."""
        return self.actor.noise_scale

    @noise_scale.setter
    def noise_scale(self, value: float) -> None:
        self.actor.noise_scale = value

    @property
    def command(self) -> float:
        """The command the governor last gave the actor."""
        return self.actor.command

    @property
    def target(self) -> float:
        """The speed the level is asked to hold."""
        return self.governor.target

    @target.setter
    def target(self, value: float) -> None:
        self.governor.target = float(value)

    def start_episode(self) -> None:
        """Forget the governor's speeds and integral before an episode's first action."""
        self.governor.reset()

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The actor's action under the command the governor sets for this observation (one at a time)."""
        self.actor.command = self.governor.command(obs)
        return self.actor.act(obs, rng)


@register_kind("governed")
def load_governed(path, meta: BehaviourMeta, state, action_space) -> GovernedPolicy:
    """A `GovernedPolicy` from a governed snapshot: the actor's tensors, the governor in `extra["governor"]`."""
    return GovernedPolicy(
        load_actor(path, meta, state, action_space), GovernorConfig(**meta.extra["governor"])
    )


def write_governed(
    source: str | Path, targets: dict[str, float], cfg: GovernorConfig, out_dir: str | Path, command: str
) -> list[Path]:
    """Write one governed level per target: the commanded actor `source` with `cfg`, targeting that speed.

    Args:
        source: A commanded snapshot (its `.safetensors` path, or the path without suffix).
        targets: Level name -> target speed (m/s); each must lie inside `cfg.command_range`.
        cfg: The governor every level uses.
        out_dir: Where `<level>.safetensors` / `.json` and `GOVERNED_WITH.md` go; other levels there are removed
            (a level no longer wanted must not be collected).
        command: The command line that asked for this, recorded in `GOVERNED_WITH.md`.

    Returns:
        The written level paths (without suffix).
    """
    source = Path(source).with_suffix("")
    meta = json.loads(Path(f"{source}.json").read_text())
    if meta.get("extra", {}).get("command") is None:
        raise ValueError(f"{source}: not a commanded snapshot (no extra.command)")
    lo, hi = cfg.command_range
    for level, speed in targets.items():
        if not lo <= speed <= hi:
            raise ValueError(f"level {level!r}: target {speed} outside the command range {cfg.command_range}")
    state = load_file(f"{source}.safetensors")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    for old in [*out_dir.glob("*.safetensors"), *out_dir.glob("*.json")]:
        old.unlink()
    written = []
    for level, speed in targets.items():
        m = BehaviourMeta(**meta)
        m.level, m.mean_speed, m.std_speed = level, None, None
        m.kind = "governed"
        m.extra = {
            "command": float(speed),
            "target_speed": float(speed),
            "commanded": True,
            "governor": cfg.to_json(),
            "source": str(source),
        }
        save_behaviour(out_dir / level, state, m)
        written.append(out_dir / level)
    (out_dir / "GOVERNED_WITH.md").write_text(
        f"# Governed levels\n\nWritten by:\n\n```bash\n{command}\n```\n\nActor: `{source}` (train step "
        f"{meta.get('train_step')}). Levels: {targets}. Governor (`research.governor.GovernorConfig`): "
        f"`{cfg.to_json()}`.\n"
    )
    return written


app = typer.Typer(
    help="Speed-governed behaviour levels (research): write them, collect them.", add_completion=False
)


@app.command()
def levels(
    source: Path = typer.Argument(
        ..., help="A commanded snapshot (.safetensors), e.g. WORK_DIR/step_01000000."
    ),
    env: str = typer.Option(
        ..., help="Gymnasium id, e.g. Hopper-v5 (where the x-velocity sits in its observation)."
    ),
    target: list[str] = typer.Option(..., help="LEVEL=SPEED (m/s), slowest first; repeat."),
    command_range: str = typer.Option(..., help="LO:HI (m/s): the commands the actor was trained on."),
    window: int = typer.Option(20, help="Steps of speed averaged by the proportional term."),
    kp: float = typer.Option(1.0, help="Proportional gain on (target - mean speed of the window)."),
    ki: float = typer.Option(0.002, help="Per-step gain of the integral of (target - speed)."),
    integral_limit: float = typer.Option(0.5, help="Bound on the integral term (m/s of command)."),
    out_dir: Path = typer.Option(None, help="Where the levels go (default behaviour/<env>/)."),
) -> None:
    """Wrap a commanded actor in a speed governor: one level per target (collect them with `collect`)."""

    vx = x_velocity_obs_index(env)
    if vx is None:
        raise typer.BadParameter(f"no known x-velocity entry in {env}'s observation", param_hint="--env")
    targets = parse_targets(target) or {}
    if any(v == "max" for v in targets.values()):
        raise typer.BadParameter("governed levels need speeds in m/s, not max", param_hint="--target")
    try:
        cfg = GovernorConfig(vx, parse_range(command_range), window, kp, ki, integral_limit)
        out = out_dir or BEHAVIOUR_DIR / env_slug(env)
        command = "python -m research.governor levels " + " ".join(shlex.quote(a) for a in sys.argv[2:])
        written = write_governed(source, targets, cfg, out, command)
    except (ValueError, FileNotFoundError) as e:
        raise typer.BadParameter(str(e)) from None
    typer.echo(f"wrote {', '.join(str(p) for p in written)}")


@app.command(context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def collect(ctx: typer.Context) -> None:
    """`gmt data collect ARGS` with the `governed` kind registered: governed levels collected like any snapshot."""
    from gmt.datagen.cli import app as data

    data(["collect", *ctx.args], prog_name="python -m research.governor collect")


if __name__ == "__main__":
    app()
