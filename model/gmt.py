"""The Goal-Masked Transformer network (paper section 2.2, A.1). Pure nn: no I/O, no normalisation."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from model.config import GMTConfig


class CausalSelfAttention(nn.Module):
    """Multi-head self-attention under a boolean mask (True = may attend)."""

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        self.n_head = cfg.n_head
        self.qkv = nn.Linear(cfg.n_embd, 3 * cfg.n_embd)
        self.proj = nn.Linear(cfg.n_embd, cfg.n_embd)
        self.dropout = cfg.dropout

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor) -> torch.Tensor:
        B, L, C = x.shape
        q, k, v = self.qkv(x).split(C, dim=2)  # 3 x [B, L, C]
        q = q.view(B, L, self.n_head, C // self.n_head).transpose(1, 2)  # [B, h, L, C/h]
        k = k.view(B, L, self.n_head, C // self.n_head).transpose(1, 2)  # [B, h, L, C/h]
        v = v.view(B, L, self.n_head, C // self.n_head).transpose(1, 2)  # [B, h, L, C/h]
        att = (q @ k.transpose(-2, -1)) * (1.0 / math.sqrt(q.shape[-1]))  # [B, h, L, L]
        att = att.masked_fill(~attn_mask, float("-inf")).softmax(dim=-1)  # [B, h, L, L]
        if self.training and self.dropout > 0:
            att = F.dropout(att, self.dropout)
        y = att @ v  # [B, h, L, C/h]
        y = y.transpose(1, 2).reshape(B, L, C)  # [B, L, C]
        return self.proj(y)


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

    def forward(self, x: torch.Tensor, attn_mask: torch.Tensor) -> torch.Tensor:
        x = x + self.drop(self.attn(self.ln1(x), attn_mask))
        x = x + self.drop(self.out(F.gelu(self.fc(self.ln2(x)), approximate="tanh")))
        return x


class ImageEncoder(nn.Module):
    """Nature-DQN CNN for uint8 frames [C, H, W] scaled to [0, 1]."""

    def __init__(self, cfg: GMTConfig) -> None:
        super().__init__()
        c, h, w = cfg.obs_shape
        self.net = nn.Sequential(
            nn.Conv2d(c, 32, 8, stride=4),
            nn.ReLU(),
            nn.Conv2d(32, 64, 4, stride=2),
            nn.ReLU(),
            nn.Conv2d(64, 64, 3, stride=1),
            nn.ReLU(),
            nn.Flatten(),
        )
        with torch.no_grad():
            n_flat = self.net(torch.zeros(1, c, h, w)).shape[1]
        self.fc = nn.Linear(n_flat, cfg.n_embd)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        B, T = x.shape[:2]
        z = self.net(x.reshape(B * T, *x.shape[2:]).float() / 255.0)  # [B*T, flat]
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
        """Goal embeddings [B, T, C]; with `blend_to`/`blend_w` each token is (1-w) E[goal] + w E[blend_to]."""
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
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Score a batch of left-padded windows.

        Args:
            goals: [B, T] goal ids (n_goals = [mask]).
            states: [B, T, *obs_shape] normalised states (uint8 frames for images).
            actions: [B, T, act_dim] in [-1, 1] (continuous) or [B, T] ids (discrete).
            timesteps: [B, T] episode timesteps.
            valid: [B, T] True for real steps, False for left padding.
            blend_to: optional [B, T] second goal of a gradual switch.
            blend_w: optional [B, T] weight of `blend_to`.

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
            x = block(x, attn_mask)
        x = self.ln_f(x).view(B, T, 3, C)  # [B, T, 3, C]
        action_out = self.action_head(x[:, :, 1])  # [B, T, act_dim] from state tokens
        if not self.cfg.discrete_actions:
            action_out = torch.tanh(action_out)
        goal_logits = self.goal_head(x[:, :, 2])  # [B, T, n_goals] from action tokens
        return action_out, goal_logits

    @staticmethod
    def attention_mask(valid: torch.Tensor) -> torch.Tensor:
        """Causal mask that hides padded keys; every token may see itself, so no row is empty.

        Args:
            valid: [B, T] True for real steps.

        Returns:
            [B, 1, 3T, 3T] boolean mask (True = may attend).
        """
        B, T = valid.shape
        L = 3 * T
        key_ok = valid.repeat_interleave(3, dim=1)  # [B, 3T]
        causal = torch.ones(L, L, dtype=torch.bool, device=valid.device).tril()  # [3T, 3T]
        eye = torch.eye(L, dtype=torch.bool, device=valid.device)  # [3T, 3T]
        return (causal & key_ok[:, None, :] | eye).unsqueeze(1)  # [B, 1, 3T, 3T]

    def num_params(self) -> int:
        """Number of parameters."""
        return sum(p.numel() for p in self.parameters())
