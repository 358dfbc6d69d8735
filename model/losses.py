"""Training loss: action loss + alpha * next-goal loss (paper section 2.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class LossParts:
    """The total loss and its parts for logging, read as floats only when asked for.

    Reading a part waits for the device; a training step that does not log never does (on a GPU the CPU then
    queues the next steps while this one runs).

    Attributes:
        total: The loss to back-propagate.
        action_loss: Detached action loss.
        goal_loss: Detached next-goal loss.
        accuracy: Detached next-goal accuracy (None when the batch has no next-goal pair).
    """

    total: torch.Tensor
    action_loss: torch.Tensor
    goal_loss: torch.Tensor
    accuracy: torch.Tensor | None

    @property
    def action(self) -> float:
        """The action loss."""
        return self.action_loss.item()

    @property
    def goal(self) -> float:
        """The next-goal loss."""
        return self.goal_loss.item()

    @property
    def goal_accuracy(self) -> float:
        """The next-goal accuracy (NaN without next-goal pairs)."""
        return float("nan") if self.accuracy is None else self.accuracy.item()


def gmt_loss(
    action_pred: torch.Tensor,
    goal_logits: torch.Tensor,
    actions: torch.Tensor,
    goals: torch.Tensor,
    valid: torch.Tensor,
    discrete_actions: bool,
    alpha: float = 1.0,
    counts: tuple[int, int] | None = None,
) -> LossParts:
    """Action loss on every real step plus next-goal cross-entropy.

    Position t's action-token output predicts the true goal of step t + 1, so the first goal of a window gets
    no loss. Goal targets are always the true labels, masked or not.

    Args:
        action_pred: [B, T, A] predictions (tanh outputs or logits).
        goal_logits: [B, T, G] next-goal logits.
        actions: [B, T, A] targets in [-1, 1], or [B, T] action ids.
        goals: [B, T] true goal ids (unmasked).
        valid: [B, T] True for real steps.
        discrete_actions: Cross-entropy on actions instead of MSE.
        alpha: Weight of the goal loss.
        counts: For one share of a larger batch (data-parallel training): the whole batch's number of action
            targets (real steps, times act_dim for continuous actions) and of next-goal pairs. Each part is
            then this share's sum divided by them, so the shares' losses add up to the whole batch's loss.
    """
    action_pred = action_pred.float()
    goal_logits = goal_logits.float()
    pair = valid[:, :-1] & valid[:, 1:]  # [B, T-1]: a_t and g_{t+1} both real
    logits = goal_logits[:, :-1][pair]  # [N, G]
    target = goals[:, 1:][pair]  # [N]
    if counts is None:
        if discrete_actions:
            a_loss = F.cross_entropy(action_pred[valid], actions[valid])
        else:
            a_loss = ((action_pred - actions) ** 2)[valid].mean()
        g_loss = F.cross_entropy(logits, target) if target.numel() > 0 else goal_logits.sum() * 0.0
    else:
        n_action, n_pairs = counts
        if discrete_actions:
            a_loss = F.cross_entropy(action_pred[valid], actions[valid], reduction="sum") / n_action
        else:
            a_loss = ((action_pred - actions) ** 2)[valid].sum() / n_action
        g_loss = F.cross_entropy(logits, target, reduction="sum") / max(n_pairs, 1)
    acc = (logits.argmax(-1) == target).float().mean() if target.numel() > 0 else None
    total = a_loss + alpha * g_loss
    return LossParts(total, a_loss.detach(), g_loss.detach(), acc)


def loss_counts(actions: torch.Tensor, valid: torch.Tensor, discrete_actions: bool) -> tuple[int, int]:
    """A batch's (action targets, next-goal pairs): the `counts` of `gmt_loss` for its shares."""
    steps = int(valid.sum())
    pairs = int((valid[:, :-1] & valid[:, 1:]).sum())
    return (steps if discrete_actions else steps * actions.shape[-1]), pairs
