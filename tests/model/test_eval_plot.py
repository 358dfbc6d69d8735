"""The evaluation figure's per-condition band."""

import warnings

import matplotlib
import numpy as np

from gmt.model.eval_plot import SMOOTH, _band

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402


def test_band_after_every_episode_fell_is_a_gap_without_warnings():
    """Steps where every seed's episode has ended (a fall) are NaN in all rows: drawn as a gap, no RuntimeWarning."""
    sig = np.full((3, 200), np.nan)
    sig[:, :50] = 1.0  # all three episodes end (fall) after 50 steps
    sig[0, 50:120] = 2.0  # one lasts longer
    fig, ax = plt.subplots()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            _band(ax, sig, "goal 0", "C0")
        mean = ax.lines[0].get_ydata()
    finally:
        plt.close(fig)
    assert np.allclose(mean[:50], 1.0)
    assert np.isfinite(mean[50 : 120 + SMOOTH - 1]).all()  # the longest episode's trailing mean
    assert np.isnan(mean[120 + SMOOTH :]).all()  # nobody left: a gap
