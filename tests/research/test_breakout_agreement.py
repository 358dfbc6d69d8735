"""research/breakout_agreement.py on the shipped five-goal Breakout model: the teacher-driven play does not depend
on the model, and the agreement is counted over the steps played."""

from pathlib import Path

import pytest

pytest.importorskip("ale_py")
pytest.importorskip("cv2")

from research.breakout_agreement import agreement  # noqa: E402

CKPT = Path(__file__).resolve().parents[2] / "checkpoints" / "breakout5-gmt"


def test_teacher_driven_play_is_the_teachers_and_model_driven_play_is_the_models():
    low = agreement(str(CKPT), 0, "strong", [3], steps=150, action_mode="argmax", teacher_drives=True)
    top = agreement(str(CKPT), 4, "strong", [3], steps=150, action_mode="argmax", teacher_drives=True)
    # the same teacher on the same seed plays the same game, whichever goal the model is asked about
    assert (low["return"], low["lives_lost"], low["steps"]) == (
        top["return"],
        top["lives_lost"],
        top["steps"],
    )
    for r in (low, top):
        assert 0.0 <= r["deciding"] <= 1.0 and 0.0 <= r["overall"] <= 1.0
        assert r["driver"] == "teacher" and 0 < r["deciding_steps"] < r["steps"] <= 150
    # the late-reacting lowest goal waits where the tracker moves: it agrees less with the tracker
    assert low["overall"] < top["overall"]
    played = agreement(str(CKPT), 4, "strong", [3], steps=150, action_mode="argmax")
    assert played["driver"] == "model" and played["steps"] <= 150
