"""`research.from_rest`: a commanded agent's start from the reset pose, measured on every 100's first segment."""

import sys

import pytest

from research import from_rest


def _run(monkeypatch, capsys, *argv: str) -> list[list[str]]:
    monkeypatch.setattr(sys, "argv", ["from_rest", *argv])
    from_rest.main()
    return [row.split() for row in capsys.readouterr().out.strip().splitlines()[1:]]


def test_a_higher_command_gets_the_shipped_hopper_agent_going_faster(monkeypatch, capsys):
    level = "behaviour/hopper-gmt/hopper/slow"
    rows = _run(monkeypatch, capsys, "--env", "Hopper-v5", "--level", level, "--commands", "1.6", "3.6",
                "--seeds", "2")  # fmt: skip
    assert [float(r[0]) for r in rows] == [1.6, 3.6]
    means = [float(r[1]) for r in rows]
    assert 0.5 < means[0] < means[1]  # moving forward, and faster when pushed harder
    assert [r[-1] for r in rows] == ["0", "0"]  # no fall within 100 steps


def test_bad_spans_are_refused(monkeypatch, capsys):
    with pytest.raises(SystemExit):
        _run(monkeypatch, capsys, "--env", "Hopper-v5", "--level", "x", "--commands", "1", "--start", "50",
             "--end", "50")  # fmt: skip


def test_a_sprint_handed_back_to_the_levels_command_is_followed_to_its_end(monkeypatch, capsys):
    """`--then`: the command drops after `--switch-at` steps; falls over `--steps` are counted with their steps."""
    level = "behaviour/hopper-gmt/hopper/slow"
    (row,) = _run(monkeypatch, capsys, "--env", "Hopper-v5", "--level", level, "--commands", "4.2", "--then",
                  "1.6", "--switch-at", "60", "--steps", "300", "--seeds", "2")  # fmt: skip
    falls = int(row[4])
    assert 0 <= falls <= 2 and (falls == 0) == (len(row) == 5)  # fall steps listed when there are any
    fell_at = [int(x.strip("(),")) for x in row[6:]] if falls else []
    assert all(100 < t <= 300 for t in fell_at)  # after the measured span, within the episode
    with pytest.raises(SystemExit):
        _run(monkeypatch, capsys, "--env", "Hopper-v5", "--level", level, "--commands", "4", "--then", "1",
             "--switch-at", "0")  # fmt: skip
