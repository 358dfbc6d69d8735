"""Replay recorded sessions against a checkpoint: how far its actions are from the ones the server answered.

Every recorded episode (`gmt.common.recording`) is fed, in lockstep through one `PolicyEngine` (as `gmt eval`
steps its episodes), the observations the server received and the goal changes of its timeline, each applied
before the act of its step exactly as the server applied them (blends included); the engine's actions are
compared with the recorded ones at every answered step. With the recording's own checkpoint, seed and action
mode the replay reproduces every action exactly: the difference is 0.

Measures: continuous actions, the mean absolute difference |a - a_rec| over the action's dimensions per step (and
its mean over steps); discrete actions, the agreement rate (share of steps with the same action). Around each goal
change (made by a client after the episode's start) the measure is also taken over the `window` steps before
and the `window` steps from the change on.

JSON (`ReplayResult.to_dict`): checkpoint, fingerprint, action_mode, metric ("mean_abs_diff" or "agreement"),
window, summary {episodes, steps, value, max_abs_diff (continuous), exact_steps, changes, before, after},
episodes [{session_id, model, fingerprint, episode, seed, steps, value, max_abs_diff, exact_steps,
changes: [{step, from_goal, to_goal, blend_steps, by, before, after}]}], per_step [{session_id, episode, t, goal,
diff}] (diff: |a - a_rec| averaged over dimensions, or 0/1 disagreement for discrete actions).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from gmt.common.recording import Recording
from gmt.model.checkpoint import Checkpoint
from gmt.model.engine import PolicyEngine


class ReplayError(ValueError):
    """A recording cannot be replayed against the checkpoint (spaces differ, unknown goal, broken timeline)."""


@dataclass
class EpisodeReplay:
    """One replayed episode: per-step differences and the goal changes in it."""

    session_id: str
    model: str
    fingerprint: str | None
    episode: int
    seed: int
    goals: np.ndarray  # [T] the goal the session pursued at each step
    diff: np.ndarray  # [T] |a - a_rec| averaged over dimensions (discrete: 1.0 where the actions differ)
    max_abs: np.ndarray  # [T] largest |a - a_rec| over dimensions (discrete: the same as diff)
    changes: list[dict] = field(default_factory=list)


@dataclass
class ReplayResult:
    """All replayed episodes against one checkpoint."""

    checkpoint: str
    fingerprint: str
    action_mode: str
    discrete: bool
    window: int
    episodes: list[EpisodeReplay]

    @property
    def metric(self) -> str:
        """The measure reported: agreement (discrete actions) or mean_abs_diff."""
        return "agreement" if self.discrete else "mean_abs_diff"

    def _value(self, diff: np.ndarray) -> float | None:
        if len(diff) == 0:
            return None
        return float(1.0 - diff.mean()) if self.discrete else float(diff.mean())

    def summary(self) -> dict:
        """Totals over every episode and every goal change."""
        diff = np.concatenate([e.diff for e in self.episodes]) if self.episodes else np.zeros(0)
        changes = [c for e in self.episodes for c in e.changes]
        before = [c["before"] for c in changes if c["before"] is not None]
        after = [c["after"] for c in changes if c["after"] is not None]
        out = {
            "episodes": len(self.episodes),
            "steps": int(len(diff)),
            "value": self._value(diff),
            "exact_steps": int(np.count_nonzero(diff == 0)),
            "changes": len(changes),
            "before": float(np.mean(before)) if before else None,
            "after": float(np.mean(after)) if after else None,
        }
        if not self.discrete:
            out["max_abs_diff"] = float(
                max((e.max_abs.max() for e in self.episodes if len(e.max_abs)), default=0)
            )
        return out

    def to_dict(self) -> dict:
        """The documented JSON form (module docstring)."""
        return {
            "checkpoint": self.checkpoint,
            "fingerprint": self.fingerprint,
            "action_mode": self.action_mode,
            "metric": self.metric,
            "window": self.window,
            "summary": self.summary(),
            "episodes": [
                {
                    "session_id": e.session_id,
                    "model": e.model,
                    "fingerprint": e.fingerprint,
                    "episode": e.episode,
                    "seed": e.seed,
                    "steps": int(len(e.diff)),
                    "value": self._value(e.diff),
                    "max_abs_diff": float(e.max_abs.max()) if len(e.max_abs) else None,
                    "exact_steps": int(np.count_nonzero(e.diff == 0)),
                    "changes": e.changes,
                }
                for e in self.episodes
            ],
            "per_step": [
                {"session_id": e.session_id, "episode": e.episode, "t": t, "goal": int(g), "diff": float(d)}
                for e in self.episodes
                for t, (g, d) in enumerate(zip(e.goals, e.diff, strict=True))
            ],
        }

    def text(self) -> str:
        """A few lines for the terminal."""
        s = self.summary()
        name = "agreement rate" if self.discrete else "mean |a - a_rec|"
        lines = [
            f"replayed {s['episodes']} episodes, {s['steps']} steps against {self.checkpoint} "
            f"({self.fingerprint[:12]}), action mode {self.action_mode}",
            f"{name}: {_fmt(s['value'])}; exact steps {s['exact_steps']}/{s['steps']}"
            + (f"; largest |a - a_rec| {s['max_abs_diff']:.6g}" if not self.discrete else ""),
            f"around {s['changes']} goal changes ({self.window} steps each side): before {_fmt(s['before'])}, "
            f"after {_fmt(s['after'])}",
        ]
        for e in self.episodes:
            lines.append(
                f"  {e.session_id[:12]} episode {e.episode}: {len(e.diff)} steps, {name} {_fmt(self._value(e.diff))}"
                + "".join(
                    f"; change at {c['step']} {c['from_goal']}->{c['to_goal']}: {_fmt(c['before'])} / "
                    f"{_fmt(c['after'])}"
                    for c in e.changes
                )
            )
        return "\n".join(lines)


def _fmt(x: float | None) -> str:
    return "n/a" if x is None else f"{x:.6g}"


@dataclass
class _Track:
    """One episode being replayed."""

    rec: Recording
    episode: int
    rows: np.ndarray
    changes: dict[int, list[dict]]  # step -> timeline entries applied before the act of that step
    first: dict


def _tracks(rec: Recording) -> list[_Track]:
    out = []
    timeline = rec.meta.get("timeline") or []
    for e in np.unique(rec.arrays["episode"]):
        rows = rec.rows_of(int(e))
        entries = [x for x in timeline if x.get("episode", 0) == int(e)]
        if not entries or entries[0]["step"] != 0 or entries[0]["by"] not in ("create", "reset"):
            raise ReplayError(
                f"recording {rec.meta['session_id']}, episode {int(e)}: its timeline does not start with the "
                "session's creation or reset"
            )
        changes: dict[int, list[dict]] = {}
        for x in entries[1:]:
            changes.setdefault(int(x["step"]), []).append(x)
        out.append(_Track(rec, int(e), rows, changes, entries[0]))
    return out


def check_compatible(rec: Recording, ckpt: Checkpoint) -> None:
    """Raise ReplayError unless the recording's observations and actions fit the checkpoint."""
    cfg = ckpt.config
    obs = rec.arrays["observations"]
    if int(np.prod(obs.shape[1:])) != int(np.prod(cfg.obs_shape)):
        raise ReplayError(
            f"recording {rec.meta.get('session_id')!r} has observations of shape {list(obs.shape[1:])}, checkpoint "
            f"{ckpt.name!r} takes {list(cfg.obs_shape)}"
        )
    acts = rec.arrays["actions"]
    discrete = acts.ndim == 1
    if discrete != cfg.discrete_actions or (not discrete and acts.shape[1] != cfg.act_dim):
        raise ReplayError(
            f"recording {rec.meta.get('session_id')!r} has {'discrete' if discrete else 'continuous'} actions of "
            f"shape {list(acts.shape[1:])}, checkpoint {ckpt.name!r} answers "
            f"{'discrete' if cfg.discrete_actions else f'{cfg.act_dim}-dimensional'} actions"
        )
    n = len(ckpt.goals)
    used = {int(x["goal"]) for x in rec.meta.get("timeline") or []}
    if any(g >= n for g in used):
        raise ReplayError(
            f"recording {rec.meta.get('session_id')!r} uses goals {sorted(used)}; checkpoint {ckpt.name!r} has {n}"
        )


def replay(
    recordings: list[Recording],
    ckpt: Checkpoint,
    action_mode: str | None = None,
    seed: int | None = None,
    window: int = 25,
    fingerprint: str = "",
) -> ReplayResult:
    """Replay every episode of `recordings` against `ckpt` in lockstep (module docstring).

    Args:
        recordings: The recordings.
        ckpt: The checkpoint to replay against.
        action_mode: Overrides the recorded action mode (default: the recording's, when the checkpoint has
            it, else the checkpoint's default).
        seed: Overrides each recording's sampler seed.
        window: Steps measured on each side of a goal change.
        fingerprint: The checkpoint's fingerprint, reported.

    Raises:
        ReplayError: a recording does not fit the checkpoint, or its timeline is broken.
    """
    engine = PolicyEngine(ckpt)
    if action_mode is not None:
        engine.check_mode(action_mode)
    tracks = []
    for rec in recordings:
        check_compatible(rec, ckpt)
        tracks += _tracks(rec)
    modes = {t.rec.meta.get("action_mode") for t in tracks}
    ctxs = []
    for tr in tracks:
        mode = action_mode or tr.rec.meta.get("action_mode")
        if mode not in engine.action_modes:
            mode = engine.default_action_mode
        s = seed if seed is not None else int(tr.rec.meta.get("seed", 0))
        ctxs.append(engine.new_context(int(tr.first["goal"]), mode, seed=s))
    reported_mode = action_mode or (modes.pop() if len(modes) == 1 else "per recording")
    n_max = max((len(t.rows) for t in tracks), default=0)
    answered = [np.zeros((len(t.rows), *t.rec.arrays["actions"].shape[1:]), np.float64) for t in tracks]
    for t in range(n_max):
        live = [i for i, tr in enumerate(tracks) if t < len(tr.rows)]
        for i in live:
            for x in tracks[i].changes.get(t, ()):
                engine.set_goal(ctxs[i], int(x["goal"]), int(x.get("blend_steps", 0)))
        obs = [tracks[i].rec.arrays["observations"][tracks[i].rows[t]] for i in live]
        acts = engine.act([ctxs[i] for i in live], obs)
        for i, a in zip(live, acts, strict=True):
            if isinstance(a, Exception):
                raise ReplayError(f"step {t} of {tracks[i].rec.meta['session_id']}: {a}")
            answered[i][t] = a
    episodes = []
    for tr, got, ctx in zip(tracks, answered, ctxs, strict=True):
        want = tr.rec.arrays["actions"][tr.rows].astype(np.float64)
        if ckpt.config.discrete_actions:
            diff = (got != want).astype(np.float64)
            max_abs = diff
        else:
            err = np.abs(got - want)
            diff, max_abs = err.mean(axis=1), err.max(axis=1)
        goals = tr.rec.arrays["goals"][tr.rows]
        ep = EpisodeReplay(
            tr.rec.meta["session_id"],
            tr.rec.meta.get("model", ""),
            tr.rec.meta.get("fingerprint"),
            tr.episode,
            int(ctx.seed),
            goals,
            diff,
            max_abs,
        )
        value = (
            (lambda d: float(1 - d.mean())) if ckpt.config.discrete_actions else (lambda d: float(d.mean()))
        )
        for step in sorted(tr.changes):
            if step >= len(diff):
                continue
            for x in tr.changes[step]:
                before, after = diff[max(step - window, 0) : step], diff[step : step + window]
                ep.changes.append(
                    {
                        "step": step,
                        "from_goal": int(goals[step - 1]) if step else int(tr.first["goal"]),
                        "to_goal": int(x["goal"]),
                        "blend_steps": int(x.get("blend_steps", 0)),
                        "by": x.get("by"),
                        "before": value(before) if len(before) else None,
                        "after": value(after) if len(after) else None,
                    }
                )
        episodes.append(ep)
    return ReplayResult(ckpt.name, fingerprint, reported_mode, ckpt.config.discrete_actions, window, episodes)


def plot_replay(result: ReplayResult, path: str | Path) -> Path:
    """Per-step difference of every episode (goal changes marked), and its mean aligned on the goal changes."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(13, 4.2))
    label = "1 - agreement" if result.discrete else "mean |a - a_rec|"
    for e in result.episodes:
        (line,) = a1.plot(e.diff, lw=0.7, alpha=0.7)
        for c in e.changes:
            a1.axvline(c["step"], color=line.get_color(), ls=":", lw=0.6)
    a1.set_xlabel("step")
    a1.set_ylabel(label)
    a1.set_title(f"replay against {result.checkpoint}: every episode (dotted: goal changes)")
    w = result.window
    aligned = []
    for e in result.episodes:
        for c in e.changes:
            s = c["step"]
            row = np.full(2 * w, np.nan)
            lo, hi = max(s - w, 0), min(s + w, len(e.diff))
            row[lo - (s - w) : hi - (s - w)] = e.diff[lo:hi]
            aligned.append(row)
    if aligned:
        m = np.nanmean(np.stack(aligned), axis=0)
        a2.plot(np.arange(-w, w), m, color="C3")
        a2.axvline(0, color="k", ls="--", lw=0.8)
    a2.set_xlabel("steps from the goal change")
    a2.set_ylabel(label)
    a2.set_title(f"mean over {len(aligned)} goal changes")
    fig.tight_layout()
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out
