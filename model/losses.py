"""Training loss: action loss + alpha * next-goal loss (paper section 2.2)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F


@dataclass
class LossParts:
    """The total loss and its parts (detached floats for logging)."""

    total: torch.Tensor
    action: float
    goal: float
    goal_accuracy: float


def gmt_loss(
    action_pred: torch.Tensor,
    goal_logits: torch.Tensor,
    actions: torch.Tensor,
    goals: torch.Tensor,
    valid: torch.Tensor,
    discrete_actions: bool,
    alpha: float = 1.0,
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
    """
    action_pred = action_pred.float()
    goal_logits = goal_logits.float()
    if discrete_actions:
        a_loss = F.cross_entropy(action_pred[valid], actions[valid])
    else:
        a_loss = ((action_pred - actions) ** 2)[valid].mean()
    pair = valid[:, :-1] & valid[:, 1:]  # [B, T-1]: a_t and g_{t+1} both real
    logits = goal_logits[:, :-1][pair]  # [N, G]
    target = goals[:, 1:][pair]  # [N]
    if target.numel() > 0:
        g_loss = F.cross_entropy(logits, target)
        acc = (logits.argmax(-1) == target).float().mean().item()
    else:
        g_loss = goal_logits.sum() * 0.0
        acc = float("nan")
    total = a_loss + alpha * g_loss
    return LossParts(total=total, action=a_loss.item(), goal=g_loss.item(), goal_accuracy=acc)
