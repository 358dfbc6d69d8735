"""Drive a local Gymnasium environment with a remote policy, following a goal schedule.

Each episode opens a session, sends every observation, applies the returned action and records the goal the
server reports with it. The per-goal segments are therefore delimited by what the server did, including goal
changes made by other clients (e.g. `curl -X PUT .../goal`) in the middle of the episode.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, TextIO

import numpy as np

from gmt.client.base import ModelInfo, PolicyClient, Session, report_info
from gmt.client.trace import Trace
from gmt.common.extras import require_module
from gmt.common.segments import MOVING_AVERAGE, Segment, measure, moving_average, table
from gmt.common.statistics import get_statistic, signal_from_step

if TYPE_CHECKING:
    import gymnasium as gym

    from gmt.client.live import LiveView
    from gmt.client.video import VideoWriter

StepHook = Callable[[int, Session], None]


def parse_goal(text: str | int) -> int | str:
    """A goal id when `text` is an integer, else a goal name."""
    if isinstance(text, int):
        return text
    t = text.strip()
    return int(t) if t.lstrip("-").isdigit() else t


def parse_schedule(text: str | None) -> list[tuple[int, int | str]]:
    """Parse "2@500,high@800" into [(500, 2), (800, "high")]: (step, goal) pairs sorted by step.

    Raises:
        ValueError: a malformed item, a negative step, or two goals for one step.
    """
    if not text or not text.strip():
        return []
    out: dict[int, int | str] = {}
    for item in text.split(","):
        goal, sep, step = item.strip().rpartition("@")
        if not sep or not goal or not step.strip().isdigit():
            raise ValueError(f"schedule item {item.strip()!r} is not GOAL@STEP (e.g. 2@500 or high@500)")
        s = int(step)
        if s in out:
            raise ValueError(f"schedule gives two goals for step {s}")
        out[s] = parse_goal(goal)
    return sorted(out.items())


def parse_every(text: str | None) -> tuple[int, int] | None:
    """Parse "LO:HI" (steps between random goal changes) into (LO, HI); None for an empty text.

    Raises:
        ValueError: not two integers with 1 <= LO <= HI.
    """
    if not text or not text.strip():
        return None
    lo, sep, hi = text.strip().partition(":")
    if not sep or not lo.strip().isdigit() or not hi.strip().isdigit() or not 1 <= int(lo) <= int(hi):
        raise ValueError(f"random schedule {text!r} is not LO:HI with 1 <= LO <= HI (e.g. 50:300)")
    return int(lo), int(hi)


def random_schedule(
    n_goals: int, steps: int, every: tuple[int, int], seed: int
) -> tuple[int, list[tuple[int, int]]]:
    """A random goal and its changes for one episode: (first goal, [(step, goal), ...]).

    The first goal is drawn uniformly; each next change comes after a uniform LO..HI steps and picks uniformly
    among the other goals. No change is made fewer than LO steps before the end, so every segment the report judges
    (after its settle-in) is at least LO steps long. A function of `seed`.
    """
    rng = np.random.default_rng([seed, 39])
    goal = int(rng.integers(n_goals))
    first, changes, t = goal, [], 0
    while n_goals > 1:
        t += int(rng.integers(every[0], every[1] + 1))
        if t > steps - every[0]:  # the last segment would be shorter than LO steps: keep the goal to the end
            break
        goal = int(rng.choice([g for g in range(n_goals) if g != goal]))
        changes.append((t, goal))
    return first, changes


@dataclass
class RunConfig:
    """What `run` does.

    Attributes:
        env_id: Gymnasium id to step locally, e.g. HalfCheetah-v5 (default: the model's own).
        model: Model name (default: the server's only model, or its only model for the environment).
        goal: Goal at step 0: an id (0 = lowest statistic) or a name.
        schedule: (step, goal) changes made by this client before acting at that step.
        episodes: Number of episodes; episode i uses seed + i for the environment and the session.
        seed: Seed of the first episode.
        steps: Maximum steps per episode (the environment's time limit is set to it).
        out: Folder for the episode-<i>.json/.csv traces, .png plots and videos (default: write nothing).
        video: Also record episode-<i>.mp4 into `out` (MuJoCo renders offscreen).
        strip_every: With `video`, also write episode-<i>-strip.png: every Nth frame side by side, captioned
            with its step and goal (0 = no strip).
        record: Ask the server to record each episode (it needs --record-dir). A recorded session is sent the
            outcome of each action (reward, terminated, truncated, the numeric info) with the next act, and after
            the last action one more act carrying the final observation (its action is not applied).
        random_schedule: (LO, HI): instead of `goal` and `schedule`, each episode starts with a random goal and
            changes to another random goal every LO..HI steps (drawn from the episode's seed).
        transport: Description of how the server is reached, for the summary.
        live: Serve a local page (`gmt.client.live`) showing the frames as they render, the running statistic
            against the goal bands, and goal buttons that change the goal through the policy server.
        live_port: Port of the --live page (0: any free port).
        live_host: Address the --live page listens on.
        statistic: Measure this statistic (an expression such as mean(abs(obs[2])), a name, or a module:function
            plug-in) instead of the one the model's goals cluster (its spec's).
        action_mode: How the server picks actions (mean/sample for continuous, argmax/sample/expert for
            discrete; default: the model's default).
        realtime: Steps per second at most (0: as fast as the server answers). Unset: with `live`, the
            environment's own rate (its render fps, 20 for HalfCheetah) once a page watches; else 0.
    """

    env_id: str | None = None
    model: str | None = None
    goal: int | str = 0
    schedule: list[tuple[int, int | str]] = field(default_factory=list)
    episodes: int = 1
    seed: int = 0
    steps: int = 1000
    out: Path | None = None
    video: bool = False
    strip_every: int = 0
    record: bool = False
    random_schedule: tuple[int, int] | None = None
    transport: str = ""
    live: bool = False
    live_port: int = 8765
    live_host: str = "127.0.0.1"
    statistic: str | None = None
    action_mode: str | None = None
    realtime: float | None = None

    def __post_init__(self) -> None:
        if self.episodes < 1 or self.steps < 1:
            raise ValueError(f"episodes and steps must be at least 1, got {self.episodes} and {self.steps}")
        if self.realtime is not None and not (self.realtime >= 0 and self.realtime < float("inf")):
            raise ValueError(
                f"--realtime must be a finite number of steps per second >= 0, got {self.realtime}"
            )


@dataclass
class EpisodeResult:
    """One episode: its trace, the per-goal segments, and the files written."""

    episode: int
    seed: int
    session_id: str
    trace: Trace
    segments: list[Segment]
    terminated: bool
    files: list[Path] = field(default_factory=list)

    def summary(self, spec: ModelInfo, cfg: RunConfig, env_id: str) -> dict:
        """JSON-ready description (without the trace); a random schedule is given as the episode drew it."""
        goal, schedule = cfg.goal, cfg.schedule
        if cfg.random_schedule is not None:
            goal, schedule = random_schedule(len(spec.goals), cfg.steps, cfg.random_schedule, self.seed)
        return {
            "model": spec.name,
            "env_id": env_id,
            "transport": cfg.transport,
            "statistic": spec.statistic,
            "episode": self.episode,
            "seed": self.seed,
            "session_id": self.session_id,
            "goal": goal,
            "schedule": [[s, g] for s, g in schedule],
            "steps": len(self.trace),
            "terminated": self.terminated,
            "goals": [g.__dict__ for g in spec.goals],
            "segments": [s.to_dict() for s in self.segments],
        }


class StatusLine:
    """A live one-line status: rewritten in place on a terminal, one line every `every` steps otherwise."""

    def __init__(self, stream: TextIO | None = None, every: int = 100) -> None:
        self.stream = stream or sys.stdout
        self.tty = self.stream.isatty()
        self.every = every
        self._width = 0

    def update(self, step: int, text: str) -> None:
        """Show `text` for `step`."""
        if self.tty:
            self.stream.write("\r" + text.ljust(self._width))
            self._width = len(text)
            self.stream.flush()
        elif step % self.every == 0:
            print(text, file=self.stream)

    def done(self) -> None:
        """End the line."""
        if self.tty and self._width:
            self.stream.write("\n")
            self._width = 0


def resolve_model(client: PolicyClient, name: str | None, env_id: str | None) -> ModelInfo:
    """The named model's spec; without a name, the server's only model or its only model for `env_id`.

    Raises:
        ValueError: no name given and no single model fits.
    """
    if name:
        return client.get_model(name)
    models = client.list_models()
    fits = [m for m in models if env_id is None or m.env_id == env_id] if len(models) > 1 else models
    if len(fits) != 1:
        if not models:
            raise ValueError("the server serves no model yet (GET /readyz says when it has loaded one)")
        listing = ", ".join(f"{m.name} ({m.env_id})" for m in models)
        raise ValueError(f"choose a model with --model; the server serves: {listing}")
    return fits[0]


def run_episode(
    session: Session,
    env: gym.Env,
    spec: ModelInfo,
    cfg: RunConfig,
    seed: int,
    on_step: StepHook | None = None,
    status: StatusLine | None = None,
    video: VideoWriter | None = None,
    live: LiveView | None = None,
) -> tuple[Trace, bool]:
    """Step one episode; returns its trace and whether the environment terminated early.

    A recorded session gets the outcome of each action with the next act, and one more act with the final
    observation (`RunConfig.record`).
    """
    schedule = dict(cfg.schedule)
    if cfg.random_schedule is not None:
        schedule = dict(random_schedule(len(spec.goals), cfg.steps, cfg.random_schedule, seed)[1])
    recorded = session.info.recording
    rate = cfg.realtime
    if rate is None:
        rate = float(env.metadata.get("render_fps") or 30) if live is not None else 0.0
    start = time.monotonic()
    trace = Trace()
    obs, _ = env.reset(seed=seed)
    terminated = truncated = False
    report: dict = {}
    try:
        for t in range(cfg.steps):
            if t in schedule:
                session.set_goal(schedule[t])
            if live is not None:
                live.apply_goals(session)  # the page's clicks
            if on_step is not None:
                on_step(t, session)
            res = session.act(obs, **report)
            before = obs
            obs, reward, terminated, truncated, info = env.step(res.action)
            if recorded:
                report = {
                    "reward": float(reward),
                    "terminated": bool(terminated),
                    "truncated": bool(truncated) or t == cfg.steps - 1,
                    "info": report_info(info),
                }
            sig = signal_from_step(
                spec.statistic, reward, info, before, res.action, plugins=cfg.statistic is not None
            )
            trace.append(t, res.step, res.goal, sig, reward, res.action)
            frame = env.render() if video is not None or (live is not None and live.wants_frame()) else None
            if video is not None:
                video.append(frame, f"step {t}  goal {spec.goal(res.goal).name}")
            if live is not None:
                live.step(t, res.goal, float(moving_average(trace.signal[-MOVING_AVERAGE:])[-1]), frame)
            if rate > 0:  # the pace a person can watch
                time.sleep(max(0.0, start + (t + 1) / rate - time.monotonic()))
            if status is not None:
                g, recent = spec.goal(res.goal), trace.signal[-MOVING_AVERAGE:]
                status.update(
                    t,
                    f"step {t:5d}  goal {g.id} ({g.name}, target {g.mean:.2f})  "
                    f"{spec.statistic} avg{len(recent)} {moving_average(recent)[-1]:+.3f}",
                )
            if terminated or truncated:
                break
        if recorded and report:
            session.act(obs, **report)  # the final observation and the last action's outcome
    finally:
        if status is not None:
            status.done()
    return trace, bool(terminated)


def _check_goals(spec: ModelInfo, cfg: RunConfig) -> None:
    for g in [cfg.goal, *(g for _, g in cfg.schedule)]:
        spec.goal(g)  # KeyError naming the model's goals
    if cfg.random_schedule is not None and cfg.schedule:
        raise ValueError("give a schedule or a random schedule, not both")
    late = [s for s, _ in cfg.schedule if s >= cfg.steps]
    if late:
        raise ValueError(f"schedule steps {late} are past the episode length ({cfg.steps} steps)")


def _write_outputs(res: EpisodeResult, spec: ModelInfo, cfg: RunConfig, env_id: str) -> list[Path]:
    from gmt.client.plots import plot_episode
    from gmt.client.trace import write_csv, write_json

    assert cfg.out is not None
    stem = cfg.out / f"episode-{res.episode}"
    title = f"{spec.name} on {env_id}, episode {res.episode} (seed {res.seed})"
    return [
        write_json(stem.with_suffix(".json"), res.summary(spec, cfg, env_id), res.trace),
        write_csv(stem.with_suffix(".csv"), res.trace),
        plot_episode(stem.with_suffix(".png"), res.trace.signal, res.segments, spec.statistic, title),
    ]


def run(
    client: PolicyClient,
    cfg: RunConfig,
    on_step: StepHook | None = None,
    echo: Callable[[str], None] = print,
    status: StatusLine | None = None,
) -> list[EpisodeResult]:
    """Run `cfg.episodes` episodes against the server behind `client`.

    Args:
        client: REST or gRPC client.
        cfg: What to run.
        on_step: Called as on_step(step, session) before each action is requested (after the schedule's
            own goal change at that step).
        echo: Where the session ids and per-segment tables are printed.
        status: Live status line (None: no live status).

    Raises:
        SpaceMismatch: the environment's spaces differ from the model's.
        KeyError: a goal that the model does not have.
        ServiceError: the server answered with an error.
        MissingExtra: the environment or the plots need an extra that is not installed.
    """
    from gmt.common.envs import make_env

    if cfg.video and cfg.out is None:
        raise ValueError("video needs an output folder (out)")
    if cfg.out is not None:
        require_module("matplotlib", "run", "the episode plots (out)")
    if cfg.transport:
        echo(f"server: {cfg.transport}")
    spec = resolve_model(client, cfg.model, cfg.env_id)
    if cfg.statistic is not None:  # measured here instead of the model's own statistic
        spec = dataclasses.replace(spec, statistic=cfg.statistic)
    get_statistic(spec.statistic, plugins=cfg.statistic is not None)  # unmeasurable: said before stepping
    env_id = cfg.env_id or spec.env_id
    _check_goals(spec, cfg)
    env = make_env(spec, env_id, max_steps=cfg.steps, render=cfg.video or cfg.live)
    if cfg.out is not None:
        cfg.out.mkdir(parents=True, exist_ok=True)
    results = []
    live = None
    if cfg.live:
        from gmt.client.live import LiveView

        live = LiveView(spec, env_id, cfg.transport, cfg.live_host, cfg.live_port)
        echo(f"live view at {live.url}")
    try:
        for ep in range(cfg.episodes):
            seed = cfg.seed + ep
            video = None
            if cfg.video and cfg.out is not None:
                from gmt.client.video import VideoWriter

                fps = env.metadata.get("render_fps") or 30
                video = VideoWriter(cfg.out / f"episode-{ep}.mp4", fps=fps, strip_every=cfg.strip_every)
            goal = cfg.goal
            if cfg.random_schedule is not None:
                goal = random_schedule(len(spec.goals), cfg.steps, cfg.random_schedule, seed)[0]
            record = True if cfg.record else None
            with client.create_session(
                spec.name, goal, seed=seed, record=record, action_mode=cfg.action_mode
            ) as session:
                echo(f"episode {ep + 1}/{cfg.episodes}: session {session.id} on {spec.name}, seed {seed}")
                if live is not None:
                    live.episode(ep, session.id)
                    if ep == 0 and cfg.realtime is None:
                        echo(f"waiting for a page to open {live.url} (Ctrl-C to stop)")
                        live.wait_for_viewer()
                try:
                    trace, terminated = run_episode(
                        session, env, spec, cfg, seed, on_step, status, video, live
                    )
                finally:
                    files = [video.close(), video.write_strip()] if video is not None else []
                    files = [f for f in files if f is not None]
            res = EpisodeResult(
                ep,
                seed,
                session.id,
                trace,
                measure(trace.goal, trace.signal, spec.goals, spec.statistic),
                terminated,
            )
            if cfg.out is not None:
                res.files = _write_outputs(res, spec, cfg, env_id) + files
            if terminated:
                echo(f"terminated early after {len(trace)} steps")
            echo(table(res.segments, spec.statistic))
            for f in res.files:
                echo(f"wrote {f}")
            results.append(res)
        if live is not None:
            live.finish()
            echo(f"the run has ended; its page stays at {live.url} until Ctrl-C")
            live.hold()
    finally:
        env.close()
        if live is not None:
            live.close()
    return results
