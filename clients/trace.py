"""An episode's step-by-step record and its JSON and CSV files."""

from __future__ import annotations

import csv
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np


@dataclass
class Trace:
    """What happened at each step of one episode.

    Attributes:
        step: Local environment step (0-based).
        server_step: Step the server reported with the action.
        goal: Goal the server reported with the action.
        signal: Per-step statistic signal after applying the action.
        reward: Environment reward.
        action: The action applied (list of floats, or an int).
    """

    step: list[int] = field(default_factory=list)
    server_step: list[int] = field(default_factory=list)
    goal: list[int] = field(default_factory=list)
    signal: list[float] = field(default_factory=list)
    reward: list[float] = field(default_factory=list)
    action: list[list[float] | int] = field(default_factory=list)

    def append(self, step: int, server_step: int, goal: int, signal: float, reward: float, action) -> None:
        """Record one step."""
        self.step.append(step)
        self.server_step.append(server_step)
        self.goal.append(goal)
        self.signal.append(float(signal))
        self.reward.append(float(reward))
        self.action.append(int(action) if np.ndim(action) == 0 else [float(a) for a in np.ravel(action)])

    def __len__(self) -> int:
        return len(self.step)

    def to_dict(self) -> dict:
        """Column-wise JSON-ready dict."""
        return {k: list(v) for k, v in self.__dict__.items()}


def write_json(path: Path, summary: dict, trace: Trace) -> Path:
    """`summary` plus the trace (under "trace") as indented JSON."""
    path.write_text(json.dumps({**summary, "trace": trace.to_dict()}, indent=1, allow_nan=True) + "\n")
    return path


def write_csv(path: Path, trace: Trace) -> Path:
    """One row per step: step, server_step, goal, signal, reward, then action (or action_0, action_1, ...)."""
    width = len(trace.action[0]) if trace.action and isinstance(trace.action[0], list) else 0
    action_cols = [f"action_{i}" for i in range(width)] if width else ["action"]
    with path.open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["step", "server_step", "goal", "signal", "reward", *action_cols])
        for i in range(len(trace)):
            a = trace.action[i]
            w.writerow(
                [
                    trace.step[i],
                    trace.server_step[i],
                    trace.goal[i],
                    repr(trace.signal[i]),
                    repr(trace.reward[i]),
                    *(map(repr, a) if isinstance(a, list) else [a]),
                ]
            )
    return path
