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
