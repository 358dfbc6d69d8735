"""Devices and batch shares of data-parallel training."""

import pytest
import torch

from gmt.model.distributed import Parallel, resolve_device
from gmt.model.losses import gmt_loss, loss_counts


def test_auto_picks_the_cpu_without_a_gpu_and_cuda_without_one_is_a_clear_error():
    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    assert resolve_device("auto").type == "cpu"
    with pytest.raises(ValueError, match="no CUDA GPU"):
        resolve_device("cuda")


def test_shares_cover_the_batch_once_and_must_be_even():
    shares = [Parallel(r, 4).rows(12) for r in range(4)]
    assert [list(range(12))[s] for s in shares] == [[0, 1, 2], [3, 4, 5], [6, 7, 8], [9, 10, 11]]
    with pytest.raises(ValueError, match="divide evenly"):
        Parallel(0, 4).rows(10)


@pytest.mark.parametrize("discrete", [False, True])
def test_the_shares_losses_add_up_to_the_whole_batchs(discrete):
    g = torch.Generator().manual_seed(0)
    B, T, A, G = 6, 5, 4, 3
    valid = torch.ones(B, T, dtype=torch.bool)
    valid[0, :2] = valid[3, :4] = False  # left padding, unevenly spread over the shares
    pred = torch.randn(B, T, A, generator=g)
    actions = torch.randint(0, A, (B, T), generator=g) if discrete else torch.rand(B, T, A, generator=g)
    logits, goals = torch.randn(B, T, G, generator=g), torch.randint(0, G, (B, T), generator=g)
    whole = gmt_loss(pred, logits, actions, goals, valid, discrete)
    counts = loss_counts(actions, valid, discrete)
    parts = [
        gmt_loss(pred[s], logits[s], actions[s], goals[s], valid[s], discrete, counts=counts)
        for s in (slice(0, 3), slice(3, 6))
    ]
    torch.testing.assert_close(sum(p.total for p in parts), whole.total)
    assert sum(p.action for p in parts) == pytest.approx(whole.action, rel=1e-6)
