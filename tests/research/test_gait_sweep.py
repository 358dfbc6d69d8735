"""`research.gait_sweep`: the 75-step window means it judges a held gait by, and a short run of the tool."""

import sys

import numpy as np
import pytest

from gmt.common.segments import held_windows, settle_in
from research import gait_sweep


def test_the_windows_it_judges_are_every_100s_measured_span_after_the_settle_in():
    v = np.random.default_rng(0).normal(size=300)
    got = held_windows(v, first=gait_sweep.FIRST, length=gait_sweep.WINDOW, every=gait_sweep.EVERY)
    starts = range(100, 300 - 75 + 1, 5)
    assert got == pytest.approx([v[a : a + 75].mean() for a in starts])
    assert gait_sweep.WINDOW == 100 - settle_in(100)  # the span every 100 measures


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
