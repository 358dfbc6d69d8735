"""`research.gait_sweep`: the 75-step window means it judges a held gait by, and a short run of the tool."""

import sys

import numpy as np
import pytest

from research import gait_sweep


def test_window_means_are_the_means_of_each_window_after_the_settle_in():
    v = np.random.default_rng(0).normal(size=300)
    got = gait_sweep.window_means(v, window=75, first=100, stride=5)
    starts = range(100, 300 - 75 + 1, 5)
    assert got == pytest.approx([v[a : a + 75].mean() for a in starts])
    assert len(gait_sweep.window_means(v[:150], window=75, first=100)) == 0  # no window fits


def test_the_tool_holds_a_shipped_level_at_each_speed(monkeypatch, capsys):
    """One seed of 1,000 Ant steps per speed: the held speeds follow the targets."""
    argv = ["gait_sweep", "--level", "behaviour/ant/slow", "--targets", "0.45", "0.6", "--seeds", "1"]
    monkeypatch.setattr(sys, "argv", argv + ["--noise-scale", "0"])
    gait_sweep.main()
    rows = capsys.readouterr().out.strip().splitlines()[1:]
    held = [float(r.split()[1]) for r in rows]
    assert len(held) == 2 and abs(held[0] - 0.45) < 0.03 and abs(held[1] - 0.6) < 0.03
    shares = [float(r.split()[-1]) for r in rows]
    assert all(0.0 <= s <= 1.0 for s in shares)
