"""Per-layer key/value ring buffers for incremental stepping of `window` models (pure tensors, no I/O).

Slot s holds the tokens of one episode's last K + 1 timesteps: token n (3 per step: goal, state, action) lives
at ring position n mod W, W = 3 (K + 1), and `tok[s, p]` records which token is there (-1 = empty). One extra
step beyond the span K is kept because the action token of step t - 1, which only becomes known at step t, still
attends to the tokens of step t - K.
"""

from __future__ import annotations

import torch

from gmt.model.config import GMTConfig


class KVCache:
    """A pool of ring buffers, one slot per session.

    Keys and values are stored head-major, so that each (slot, head) is one contiguous [W, C/h] block that the
    attention product reads without a copy.

    Attributes:
        k: [n_layer, n_slots, n_head, W, C/h] keys.
        v: [n_layer, n_slots, n_head, W, C/h] values.
        tok: [n_slots, W] token index held at each ring position (-1 = empty).

    All three live on `device` (the torch step's device, e.g. a GPU's memory, allocated once for the pool).
    """

    def __init__(self, cfg: GMTConfig, n_slots: int, device: torch.device | str = "cpu") -> None:
        if cfg.attention != "window":
            raise ValueError("a key/value cache is exact only for attention='window' models")
        self.width = 3 * (cfg.context_length + 1)
        self.device = torch.device(device)
        shape = (cfg.n_layer, n_slots, cfg.n_head, self.width, cfg.n_embd // cfg.n_head)
        self.k = torch.zeros(shape, device=self.device)
        self.v = torch.zeros_like(self.k)
        self.tok = torch.full((n_slots, self.width), -1, dtype=torch.int64, device=self.device)

    @property
    def n_slots(self) -> int:
        """Number of slots."""
        return self.tok.shape[0]

    def grow(self, n_slots: int) -> None:
        """Enlarge the pool to `n_slots` slots, keeping every slot's contents."""
        extra = n_slots - self.n_slots
        if extra <= 0:
            return
        L, _, h, W, d = self.k.shape
        dev = self.device
        self.k = torch.cat([self.k, torch.zeros(L, extra, h, W, d, device=dev)], dim=1)
        self.v = torch.cat([self.v, torch.zeros(L, extra, h, W, d, device=dev)], dim=1)
        self.tok = torch.cat([self.tok, torch.full((extra, W), -1, dtype=torch.int64, device=dev)])

    def write(self, layer: int, slot: int, ring: torch.Tensor, k: torch.Tensor, v: torch.Tensor) -> None:
        """Store keys and values `k`, `v` [n, C] of one slot's tokens at ring positions `ring` [n]."""
        _, _, h, _, d = self.k.shape
        n = ring.shape[0]
        ring = ring.to(self.device)
        self.k[layer, slot][:, ring] = k.view(n, h, d).transpose(0, 1)  # [h, n, C/h]
        self.v[layer, slot][:, ring] = v.view(n, h, d).transpose(0, 1)

    def clear(self, slots: torch.Tensor) -> None:
        """Forget everything held in `slots` ([B] int64).

        Keys and values are zeroed too: an empty position is masked, but a masked NaN (left by a step whose
        forward failed) would still turn the attention sum into NaN, since 0 x NaN is NaN.
        """
        slots = slots.to(self.device)
        self.tok[slots] = -1
        self.k[:, slots] = 0.0
        self.v[:, slots] = 0.0
