"""The Goal-Masked Transformer network (paper section 2.2, A.1). Pure nn: no I/O, no normalisation."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from gmt.model.config import GMTConfig


class CausalSelfAttention(nn.Module):
    """Multi-head self-attention under a boolean mask (True = may attend)."""

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        self.n_head = cfg.n_head
        self.qkv = nn.Linear(cfg.n_embd, 3 * cfg.n_embd)
        self.proj = nn.Linear(cfg.n_embd, cfg.n_embd)
        self.dropout = cfg.dropout

    def _heads(self, x: torch.Tensor) -> torch.Tensor:
        B, L, C = x.shape
        return x.view(B, L, self.n_head, C // self.n_head).transpose(1, 2)  # [B, h, L, C/h]

    def _attend(
        self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: torch.Tensor
    ) -> torch.Tensor:
        """Attention of queries `q` [B, Lq, C] over keys and values [B, Lk, C], projected: [B, Lq, C]."""
        return self._attend_heads(self._heads(q), self._heads(k), self._heads(v), attn_mask)

    def _attend_heads(
        self, q: torch.Tensor, k: torch.Tensor, v: torch.Tensor, attn_mask: torch.Tensor
    ) -> torch.Tensor:
        """`_attend` with q [B, h, Lq, C/h] and k, v [B, h, Lk, C/h] already split into heads."""
        # Explicit attention rather than F.scaled_dot_product_attention: on CPU SDPA's result depends on the
        # batch size in the last bit (batched and unbatched serving must agree exactly), and its backward is
        # 2x slower here.
        B, h, Lq, d = q.shape
        att = (q @ k.transpose(-2, -1)) * (1.0 / math.sqrt(d))  # [B, h, Lq, Lk]
        att = att.masked_fill(~attn_mask, float("-inf")).softmax(dim=-1)
        if self.training and self.dropout > 0:
            att = F.dropout(att, self.dropout)
        y = att @ v  # [B, h, Lq, C/h]
        return self.proj(y.transpose(1, 2).reshape(B, Lq, h * d))  # [B, Lq, C]

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor, kv_out: list | None = None) -> torch.Tensor:
        """Attend over `x` [B, L, C]; appends this layer's (keys, values) [B, L, C] to `kv_out` if given."""
        q, k, v = self.qkv(x).split(x.shape[-1], dim=2)  # 3 x [B, L, C]
        if kv_out is not None:
            kv_out.append((k, v))
        return self._attend(q, k, v, attn_mask)

    def forward_cached(
        self,
        x: torch.Tensor,
        attn_mask: torch.Tensor,
        k_cache: torch.Tensor,
        v_cache: torch.Tensor,
        slots: torch.Tensor,
        pos: torch.Tensor,
        view,
    ) -> torch.Tensor:
        """Attend from new tokens `x` [B, n, C] over the cached tokens of their slots.

        The new keys and values are first written to ring positions `pos` [B, n] of `slots` [B] in the
        head-major caches [n_slots, h, W, C/h]; `attn_mask` [B, 1, n, W] says which ring positions each new
        token sees. `view` is the same slots as a slice when they are consecutive: the caches are then read
        without a copy.
        """
        q, k, v = self.qkv(x).split(x.shape[-1], dim=2)  # 3 x [B, n, C]
        q, k, v = self._heads(q), self._heads(k), self._heads(v)  # 3 x [B, h, n, C/h]
        B, h, n, _ = k.shape
        heads = torch.arange(h, device=k.device)[None, :, None]  # [1, h, 1]
        at = (slots[:, None, None], heads, pos[:, None, :])  # broadcast to [B, h, n]
        k_cache[at] = k
        v_cache[at] = v
        return self._attend_heads(q, view(k_cache), view(v_cache), attn_mask)  # keys, values [B, h, W, C/h]


class Block(nn.Module):
    """Pre-LayerNorm transformer block with a tanh-approximated GELU MLP (cheap on CPU)."""

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        self.ln1 = nn.LayerNorm(cfg.n_embd)
        self.attn = CausalSelfAttention(cfg)
        self.ln2 = nn.LayerNorm(cfg.n_embd)
        self.fc = nn.Linear(cfg.n_embd, 4 * cfg.n_embd)
        self.out = nn.Linear(4 * cfg.n_embd, cfg.n_embd)
        self.drop = nn.Dropout(cfg.dropout) if cfg.dropout > 0 else nn.Identity()

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor, kv_out: list | None = None) -> torch.Tensor:
        x = x + self.drop(self.attn(self.ln1(x), attn_mask, kv_out))
        return x + self.drop(self.mlp(x))

    def mlp(self, x: torch.Tensor) -> torch.Tensor:
        """The feed-forward half (pre-norm included)."""
        return self.out(F.gelu(self.fc(self.ln2(x)), approximate="tanh"))

    def forward_cached(
        self, x: torch.Tensor, attn_mask: torch.Tensor, k_cache, v_cache, slots, pos, view
    ) -> torch.Tensor:
        """`forward` for new tokens attending over a key/value cache (see `CausalSelfAttention.forward_cached`)."""
        x = x + self.attn.forward_cached(self.ln1(x), attn_mask, k_cache, v_cache, slots, pos, view)
        return x + self.mlp(x)


class ImageEncoder(nn.Module):
    """A CNN for uint8 frames [C, H, W] scaled to [0, 1] (`GMTConfig.image_encoder`)."""

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        c, h, w = cfg.obs_shape
        self.fine = cfg.image_encoder == "fine"
        if self.fine:
            # x and y in [-1, 1], one plane each, appended to every frame stack (CoordConv, Liu et al. 2018)
            ys, xs = torch.meshgrid(torch.linspace(-1, 1, h), torch.linspace(-1, 1, w), indexing="ij")
            self.register_buffer("coords", torch.stack((xs, ys))[None], persistent=False)  # [1, 2, H, W]
            layers = [(c + 2, 32, 4, 2), (32, 64, 4, 2), (64, 64, 3, 2), (64, 64, 3, 1)]
        else:
            layers = [(c, 32, 8, 4), (32, 64, 4, 2), (64, 64, 3, 1)]
        mods: list[nn.Module] = []
        for c_in, c_out, k, stride in layers:
            mods += [nn.Conv2d(c_in, c_out, k, stride=stride), nn.ReLU()]
        self.net = nn.Sequential(*mods, nn.Flatten())
        with torch.no_grad():
            n_flat = self.net(torch.zeros(1, layers[0][0], h, w)).shape[1]
        self.fc = nn.Linear(n_flat, cfg.n_embd)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T = x.shape[:2]
        z = x.reshape(B * T, *x.shape[2:]).float() / 255.0  # [B*T, C, H, W]
        if self.fine:
            z = torch.cat((z, self.coords.expand(B * T, -1, -1, -1)), dim=1)  # [B*T, C + 2, H, W]
        z = self.net(z)  # [B*T, flat]
        return torch.tanh(self.fc(z)).view(B, T, -1)  # [B, T, C]


class GMT(nn.Module):
    """Causal transformer over interleaved (goal, state, action) tokens.

    The action a_t is predicted from the output at state token s_t; the next goal g_{t+1} from the output at
    action token a_t.
    """

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        self.cfg = cfg
        C = cfg.n_embd
        self.goal_emb = nn.Embedding(cfg.n_goals + 1, C)  # last row: [mask]
        if cfg.conditioning == "return":
            self.return_emb = nn.Linear(1, C)  # Decision Transformer: return-to-go tokens
        self.state_emb = ImageEncoder(cfg) if cfg.is_image else nn.Linear(cfg.obs_shape[0], C)
        self.action_emb = nn.Embedding(cfg.act_dim, C) if cfg.discrete_actions else nn.Linear(cfg.act_dim, C)
        self.time_emb = nn.Embedding(cfg.max_timestep, C)
        self.ln_in = nn.LayerNorm(C)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layer))
        self.ln_f = nn.LayerNorm(C)
        self.action_head = nn.Linear(C, cfg.act_dim)
        self.goal_head = nn.Linear(C, cfg.n_goals)
        self.apply(self._init_weights)
        for name, p in self.named_parameters():
            if name.endswith("out.weight") or name.endswith("proj.weight"):
                nn.init.normal_(p, mean=0.0, std=0.02 / math.sqrt(2 * cfg.n_layer))

    @staticmethod
    def _init_weights(m: nn.Module) -> None:
        if isinstance(m, nn.Linear):
            nn.init.normal_(m.weight, mean=0.0, std=0.02)
            if m.bias is not None:
                nn.init.zeros_(m.bias)
        elif isinstance(m, nn.Embedding):
            nn.init.normal_(m.weight, mean=0.0, std=0.02)

    def embed_goals(
        self, goals: torch.Tensor, blend_to: torch.Tensor | None = None, blend_w: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Goal embeddings [B, T, C]; with `blend_to`/`blend_w` each token is (1-w) E[goal] + w E[blend_to].

        With `return` conditioning, `goals` holds returns-to-go [B, T] (floats) and there is no blending.
        """
        if self.cfg.conditioning == "return":
            return self.return_emb((goals.float() / self.cfg.return_scale).unsqueeze(-1))  # [B, T, C]
        e = self.goal_emb(goals)  # [B, T, C]
        if blend_to is None:
            return e
        w = blend_w.unsqueeze(-1).to(e.dtype)  # [B, T, 1]
        return torch.lerp(e, self.goal_emb(blend_to), w)

    def forward(
        self,
        goals: torch.Tensor,
        states: torch.Tensor,
        actions: torch.Tensor,
        timesteps: torch.Tensor,
        valid: torch.Tensor,
        blend_to: torch.Tensor | None = None,
        blend_w: torch.Tensor | None = None,
        last_only: bool = False,
        kv_out: list | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Score a batch of left-padded sequences (the reference forward).

        Args:
            goals: [B, T] goal ids (n_goals = [mask]), or returns-to-go with `return` conditioning.
            states: [B, T, *obs_shape] normalised states (uint8 frames for images).
            actions: [B, T, act_dim] in [-1, 1] (continuous) or [B, T] ids (discrete).
            timesteps: [B, T] episode timesteps.
            valid: [B, T] True for real steps, False for left padding.
            blend_to: optional [B, T] second goal of a gradual switch.
            blend_w: optional [B, T] weight of `blend_to`.
            last_only: apply the heads at the last step only (serving): outputs are [B, 1, ...].
            kv_out: if a list, each layer's (keys, values) [B, 3T, C] are appended to it.

        Returns:
            action predictions [B, T, act_dim] (tanh-squashed for continuous, logits for discrete) and
            next-goal logits [B, T, n_goals] (position t predicts the goal of t + 1).
        """
        B, T = goals.shape
        C = self.cfg.n_embd
        t_emb = self.time_emb(timesteps.clamp(0, self.cfg.max_timestep - 1))  # [B, T, C]
        g = self.embed_goals(goals, blend_to, blend_w) + t_emb  # [B, T, C]
        s = self.state_emb(states) + t_emb  # [B, T, C]
        a = self.action_emb(actions) + t_emb  # [B, T, C]
        x = torch.stack((g, s, a), dim=2).reshape(B, 3 * T, C)  # [B, 3T, C]: g0 s0 a0 g1 s1 a1 ...
        x = self.ln_in(x)
        attn_mask = self.attention_mask(valid)  # [B, 1, 3T, 3T]
        for block in self.blocks:
            x = block(x, attn_mask, kv_out)
        if last_only:
            # Heads over the last step's 3 tokens, not only its state token: a one-row product would take a
            # GEMV path whose last bit differs from the batched GEMM (batched == unbatched must hold exactly).
            x = self.ln_f(x[:, -3:])  # [B, 3, C]
            return self._action_head(x)[:, None, 1], self.goal_head(x)[:, None, 2]  # [B, 1, A], [B, 1, G]
        x = self.ln_f(x).view(B, T, 3, C)  # [B, T, 3, C]
        return self._action_head(x[:, :, 1]), self.goal_head(x[:, :, 2])

    def _action_head(self, x: torch.Tensor) -> torch.Tensor:
        """Action predictions from state-token outputs [..., C]: tanh for continuous, logits for discrete."""
        out = self.action_head(x)
        return out if self.cfg.discrete_actions else torch.tanh(out)

    def attention_mask(self, valid: torch.Tensor) -> torch.Tensor:
        """Causal mask that hides padded keys (and, for `window` attention, keys older than K timesteps).

        Every token may see itself, so no row is empty.

        Args:
            valid: [B, T] True for real steps.

        Returns:
            [B, 1, 3T, 3T] boolean mask (True = may attend).
        """
        B, T = valid.shape
        L = 3 * T
        key_ok = valid.repeat_interleave(3, dim=1)  # [B, 3T]
        causal = torch.ones(L, L, dtype=torch.bool, device=valid.device).tril()  # [3T, 3T]
        if self.cfg.attention == "window":
            step = torch.arange(L, device=valid.device) // 3  # [3T] timestep of each token
            causal &= (step[:, None] - step[None, :]) < self.cfg.context_length
        eye = torch.eye(L, dtype=torch.bool, device=valid.device)  # [3T, 3T]
        return (causal & key_ok[:, None, :] | eye).unsqueeze(1)  # [B, 1, 3T, 3T]

    def step(
        self,
        prev_actions: torch.Tensor,
        goals: torch.Tensor,
        states: torch.Tensor,
        timesteps: torch.Tensor,
        cache,
        slots: torch.Tensor,
        blend_to: torch.Tensor | None = None,
        blend_w: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """One incremental step of a `window` model: only the newest tokens go through the network.

        The new tokens of each row are the action taken at the previous step (a dummy at timestep 0), the goal
        and the state; their keys and values join the row's slot of `cache` (`gmt.model.kv_cache.KVCache`).

        Args:
            prev_actions: [B, act_dim] (or [B] ids) action taken at timestep t - 1.
            goals: [B] goal ids of timestep t.
            states: [B, *obs_shape] normalised states of timestep t.
            timesteps: [B] t.
            cache: the key/value pool.
            slots: [B] slot of each row (a slot repeats only in identical rows: padding).
            blend_to: optional [B] second goal of a gradual switch.
            blend_w: optional [B] weight of `blend_to`.

        Returns:
            [B, act_dim] action predictions at the state token (as `forward`).
        """
        W = cache.width
        t = timesteps
        t_emb = self.time_emb(t.clamp(0, self.cfg.max_timestep - 1))  # [B, C]
        tp_emb = self.time_emb((t - 1).clamp(0, self.cfg.max_timestep - 1))  # [B, C]
        a = self.action_emb(prev_actions) + tp_emb  # [B, C]
        bt = None if blend_to is None else blend_to[:, None]
        bw = None if blend_w is None else blend_w[:, None]
        g = self.embed_goals(goals[:, None], bt, bw)[:, 0] + t_emb  # [B, C]
        s = self.state_emb(states[:, None])[:, 0] + t_emb  # [B, C]
        x = self.ln_in(torch.stack((a, g, s), dim=1))  # [B, 3, C]: a_{t-1} g_t s_t
        idx = torch.stack((3 * t - 1, 3 * t, 3 * t + 1), dim=1)  # [B, 3] token indices
        pos = idx % W  # [B, 3] ring positions
        cache.tok[slots[:, None].expand_as(pos), pos] = idx.masked_fill(idx < 0, -1)
        key = cache.tok[slots]  # [B, W] token index at each ring position
        kstep = torch.div(key, 3, rounding_mode="floor")[:, None, :]  # [B, 1, W]
        qstep = torch.div(idx, 3, rounding_mode="floor")[:, :, None]  # [B, 3, 1]
        see = (
            (key[:, None, :] >= 0)
            & (key[:, None, :] <= idx[:, :, None])
            & (qstep - kstep < self.cfg.context_length)
        )
        # every token sees itself: no empty row
        see |= torch.arange(W, device=pos.device)[None, None, :] == pos[:, :, None]
        attn_mask = see.unsqueeze(1)  # [B, 1, 3, W]
        view = self._slot_reader(slots)
        for layer, block in enumerate(self.blocks):
            x = block.forward_cached(x, attn_mask, cache.k[layer], cache.v[layer], slots, pos, view)
        return self._action_head(self.ln_f(x))[
            :, 2
        ]  # [B, act_dim] from the state token (3 rows: see forward)

    @staticmethod
    def _slot_reader(slots: torch.Tensor):
        """A function reading rows `slots` [B] of a cache [n_slots, ...]: a view where it can, else a gather."""
        # No broadcast view for repeated slots: torch folds a product with a stride-0 batch into one larger
        # matrix product, whose last bits differ from the per-row products of other batches.
        B, first = slots.shape[0], int(slots[0])
        if bool((slots == torch.arange(first, first + B, device=slots.device)).all()):  # consecutive slots
            return lambda cache: cache[first : first + B]
        return lambda cache: cache.index_select(0, slots)

    def num_params(self) -> int:
        """Number of parameters."""
        return sum(p.numel() for p in self.parameters())
