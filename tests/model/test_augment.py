"""Frame augmentation: one shift and rotation per sequence, identity when off."""

import numpy as np
import torch

from gmt.model.augment import augment_frames


def _dot(B=3, T=2, C=4, H=16, W=16, y=8, x=8):
    s = torch.zeros(B, T, C, H, W, dtype=torch.uint8)
    s[..., y, x] = 200
    return s


def test_no_shift_and_no_rotation_is_the_identity():
    s = torch.randint(0, 256, (2, 3, 4, 12, 12), dtype=torch.uint8)
    out = augment_frames(s, 0.0, 0.0, torch.Generator().manual_seed(0))
    assert out.dtype == torch.float32 and out.shape == s.shape
    torch.testing.assert_close(out, s.float(), atol=1e-3, rtol=0)


def test_a_shift_moves_every_frame_of_a_sequence_alike():
    out = augment_frames(_dot(), 3.0, 0.0, torch.Generator().manual_seed(1))
    where = []
    for b in range(3):
        peaks = {
            tuple(np.unravel_index(int(out[b, t, c].argmax()), out.shape[-2:]))
            for t in range(2)
            for c in range(4)
        }
        assert len(peaks) == 1  # the same transform for every step and frame of the sequence
        (p,) = peaks
        assert abs(p[0] - 8) <= 3 and abs(p[1] - 8) <= 3  # moved by at most max_shift
        where.append(p)
        torch.testing.assert_close(out[b].sum(), torch.tensor(200.0 * 8), rtol=1e-4, atol=0)  # all of the dot
    assert len(set(where)) > 1  # sequences get their own transforms


def test_rotation_turns_about_the_centre_and_is_seeded():
    s = _dot(B=1, y=8, x=14)  # a dot right of the centre
    a = augment_frames(s, 0.0, 30.0, torch.Generator().manual_seed(2))
    b = augment_frames(s, 0.0, 30.0, torch.Generator().manual_seed(2))
    torch.testing.assert_close(a, b)
    y, x = np.unravel_index(int(a[0, 0, 0].argmax()), a.shape[-2:])
    r = np.hypot(y - 7.5, x - 7.5)
    assert abs(r - np.hypot(0.5, 6.5)) <= 1.5  # same distance from the centre
