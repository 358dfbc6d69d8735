"""The forward passes behind an act: the network's output for a batch of a session pool's slots.

- the **incremental** path (`window` models): only the newest tokens of each session, the action taken at the
  previous step, the goal and the state, go through the network, attending over the key/value cache; computed
  by the native kernel (`gmt.model.native`) or in torch;
- the **recompute** path (the reference, and the only exact path for `full` models): the whole history window
  through the network, heads at the last position only.

Both give the same actions (fp32, to rounding). A session adopted from a store gets its cache rebuilt from its
stored steps (`Predictor.rebuild_caches`).
"""

from __future__ import annotations

import numpy as np
import torch

from gmt.model.gmt import GMT
from gmt.model.pool import SessionPool

TORCH_ROW_MULTIPLE = 8  # the torch step runs batches padded to a multiple of this many rows (exactness)


class Predictor:
    """Runs the network over slots of one pool.

    Args:
        model: The network, in eval mode.
        pool: The pool whose slots it reads (and whose cache the incremental path advances).
        incremental: Use the key/value-cache path, else the recompute path.
        native: The native step (`gmt.model.native.NativeStep`) for the incremental path, or None (torch).
        device: Where the torch step runs (the model's parameters and the pool's cache live there); inputs are
            copied to it and predictions back, once per batch.
    """

    def __init__(
        self, model: GMT, pool: SessionPool, incremental: bool, native=None, device: str = "cpu"
    ) -> None:
        self.model, self.pool, self.incremental, self.native = model, pool, incremental, native
        self.device = torch.device(device)
        self.K = model.cfg.context_length
        self._arange_h = np.arange(pool.H)

    def __call__(self, slots, t, g, goal, w, states) -> np.ndarray:
        """[B, A] float32 predictions (logits for discrete actions) for the rows' next step.

        Args:
            slots: [B] slots; t: [B] their steps; g: [B] goal tokens; goal: [B] goals faded in; w: [B] their
                weights; states: [B, *obs_shape] normalised observations.
        """
        if self.native is not None:
            return self._native_step(slots, t, g, goal, w, states)
        with torch.inference_mode():
            if self.incremental:
                pred = self._incremental(slots, t, g, goal, w, states)
            else:
                pred = self._recompute(slots, t, g, goal, w, states)
            return pred.float().cpu().numpy()  # [B, A]

    def _t(self, x) -> torch.Tensor:
        """A numpy array (or tensor) as a tensor on the step's device."""
        return (torch.from_numpy(x) if isinstance(x, np.ndarray) else x).to(
            self.device
        )  # (a no-op on the CPU)

    @torch.inference_mode()
    def rebuild_caches(self, slots: list[int]) -> None:
        """Recompute the slots' key/value caches from their histories (sessions adopted from a store).

        With the native step the stored steps are replayed through it (the kernel that computed the caches in
        the first place, so a session continues bit for bit), every slot at once: one batched call per step index,
        the step being batch invariant, so each row's cache is what its own replay would write. The action
        before a slot's oldest stored step is not stored: a zero stands in for it, which changes only keys that
        no later step attends to (the stored history spans the receptive field). Without the native step, one
        reference forward over each slot's stored steps.
        """
        p = self.pool
        rows = np.asarray(slots, dtype=np.int64)  # [B]
        p.cache.clear(torch.from_numpy(rows))
        if self.native is None:
            for slot in slots:
                self._forward_cache(slot)
            return
        t = p.step[rows].astype(np.int64)  # [B] steps taken
        n = np.minimum(t, p.H)  # [B] steps stored
        for i in range(int(n.max(initial=0))):
            live = n > i  # [B] rows that still have a stored step i
            r, s = rows[live], (t - n)[live] + i  # [b] slots, [b] the step each replays now
            pos = s % p.H  # [b] ring positions
            prev = p.h_action[r, (s - 1) % p.H] if i else np.zeros_like(p.h_action[r, 0])  # [b, A]
            self.native(
                prev,
                p.h_goal[r, pos],
                p.h_state[r, pos],
                s,
                p.cache,
                r,
                p.h_blend_to[r, pos],
                p.h_blend_w[r, pos],
            )

    def _forward_cache(self, slot: int) -> None:
        """One (cleared) slot's cache by the reference forward over its stored steps."""
        p, cache = self.pool, self.pool.cache
        t = int(p.step[slot])
        n = min(t, p.H)
        if n == 0:
            return
        pos = np.arange(t - n, t) % p.H
        kv: list = []
        self.model(
            self._t(p.h_goal[slot, pos][None]),
            self._t(p.h_state[slot, pos][None]),
            self._t(p.h_action[slot, pos][None]),
            self._t(torch.arange(t - n, t)[None]),
            self._t(torch.ones(1, n, dtype=torch.bool)),
            self._t(p.h_blend_to[slot, pos][None]),
            self._t(p.h_blend_w[slot, pos][None]),
            last_only=True,
            kv_out=kv,
        )
        keep = min(n, self.K + 1) * 3  # tokens of the last K + 1 steps
        tok = torch.arange(3 * (t - n), 3 * t)[-keep:]  # [keep] token indices
        ring = tok % cache.width
        for layer, (k, v) in enumerate(kv):
            cache.write(layer, slot, ring, k[0, -keep:], v[0, -keep:])
        cache.tok[slot, ring.to(cache.device)] = tok.to(cache.device)

    def _native_step(self, slots, t, g, goal, w, states) -> np.ndarray:
        """The incremental step by the native kernel: batch invariant by construction, so no lone-row or
        slot-order handling. Returns [B, A] float32."""
        p = self.pool
        prev = p.h_action[slots, (t - 1) % p.H]  # [B, A] (junk where t == 0)
        prev[t == 0] = 0
        blend = bool((w > 0).any())
        return self.native(prev, g, states, t, p.cache, slots, goal if blend else None, w if blend else None)

    def _incremental(self, slots, t, g, goal, w, states) -> torch.Tensor:
        n = len(slots)
        if n % TORCH_ROW_MULTIPLE:
            # The BLAS kernel behind a matrix product depends on its row count, and a row's last bit on the
            # kernel: one row takes a GEMV path, and on AVX-512 here the rows past a multiple of 4 take another
            # micro-kernel. Padding every batch to a multiple of 8 rows (repeats of the last row: same slot,
            # same values) keeps batched == unbatched exact.
            pad = np.concatenate([np.arange(n), np.full(-n % TORCH_ROW_MULTIPLE, n - 1)])
            return self._incremental(*[x[pad] for x in (slots, t, g, goal, w, states)])[:n]
        if (
            np.diff(slots) < 0
        ).any():  # rows in slot order: consecutive slots are read from the cache as views
            order = np.argsort(slots, kind="stable")
            sorted_rows = [x[order] for x in (slots, t, g, goal, w, states)]
            out = self._incremental(*sorted_rows)
            return out[self._t(np.argsort(order))]
        p = self.pool
        prev = p.h_action[slots, (t - 1) % p.H]  # [B, A] (junk where t == 0)
        prev[t == 0] = 0
        blend = bool((w > 0).any())
        return self.model.step(
            self._t(prev),
            self._t(g),
            self._t(states),
            self._t(t),
            p.cache,
            self._t(slots),
            self._t(goal) if blend else None,
            self._t(w) if blend else None,
        )

    def _recompute(self, slots, t, g, goal, w, states) -> torch.Tensor:
        p, H = self.pool, self.pool.H
        idx = t[:, None] - H + 1 + self._arange_h[None, :]  # [B, H] timesteps of the window
        valid = idx >= 0  # [B, H]
        pos = idx % H
        rows = slots[:, None]
        goals, blend_to, blend_w = p.h_goal[rows, pos], p.h_blend_to[rows, pos], p.h_blend_w[rows, pos]
        st, ac = p.h_state[rows, pos], p.h_action[rows, pos]  # [B, H, *obs], [B, H, A]
        goals[:, -1], blend_to[:, -1], blend_w[:, -1], st[:, -1], ac[:, -1] = g, goal, w, states, 0
        pad = ~valid
        goals[pad], blend_to[pad], blend_w[pad], st[pad], ac[pad] = 0, 0, 0, 0, 0
        blend = bool((blend_w > 0).any())
        pred, _ = self.model(
            self._t(goals),
            self._t(st),
            self._t(ac),
            self._t(np.where(valid, idx, 0)),
            self._t(valid),
            self._t(blend_to) if blend else None,
            self._t(blend_w) if blend else None,
            last_only=True,
        )
        return pred[:, 0]  # [B, A]
