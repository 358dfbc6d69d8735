"""The Decision Transformer baseline under the goal-switching protocol (docs/architecture.md, paper A.2.3).

A Decision Transformer (a `GMT` with `return` conditioning) is steered by a return-to-go instead of a goal id.
Goal g's target is the mean episode return of g's trajectories in the training data (recorded in gmt.json at
training time). The return-to-go starts at the first goal's target and drops by every reward received; when the
schedule switches to goal b at step s, it becomes b's target minus the return already received, as the paper
did. Episodes are judged exactly as GMT's (`gmt.model.evaluate.judge`: same conditions, seeds, segments and
tolerances), so the two share one table.

Every step recomputes each episode's window with the reference forward (no key/value cache: the engine serves
goal-conditioned models only). Actions are the model's mean (deterministic), as in the Decision Transformer paper.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from tqdm import tqdm

from gmt.common.statistics import get_statistic, signal_from_step
from gmt.model.checkpoint import Checkpoint
from gmt.model.evaluate import Condition, EvalResult, judge, protocol
from gmt.model.tokens import pad_left


def target_returns(ckpt: Checkpoint) -> np.ndarray:
    """[n_goals] each goal's return target, from gmt.json's `decision_transformer.goal_returns`."""
    if ckpt.config.conditioning != "return":
        raise ValueError(
            f"{ckpt.name} is not a Decision Transformer (conditioning {ckpt.config.conditioning!r})"
        )
    try:
        returns = np.asarray(ckpt.meta["decision_transformer"]["goal_returns"], dtype=np.float64)
    except KeyError:
        raise ValueError(f"{ckpt.name}: gmt.json has no decision_transformer.goal_returns") from None
    if returns.shape != (len(ckpt.goals),) or not np.isfinite(returns).all():
        raise ValueError(f"{ckpt.name}: goal_returns {returns.tolist()} do not match {len(ckpt.goals)} goals")
    return returns


def returns_to_go(targets: np.ndarray, goal_at, rewards: np.ndarray, t: int) -> float:
    """The return-to-go fed at step `t` of one episode.

    Args:
        targets: [n_goals] return target per goal.
        goal_at: The episode's goal schedule (step -> goal).
        rewards: [>= t] rewards received so far (entries before `t` are used).
        t: The step about to be taken.

    The target of the goal in force since its last switch at step s, minus the rewards received from step 0
    (the paper: "the new goal's return minus the return already received").
    """
    return float(targets[goal_at(t)] - rewards[:t].sum())


@torch.inference_mode()
def evaluate_dt(
    ckpt: Checkpoint,
    seeds: int | list[int] = 15,
    steps: int = 1000,
    conditions: list[Condition] | None = None,
    progress: bool = True,
) -> EvalResult:
    """Play every condition for every seed with the Decision Transformer, all episodes in lockstep.

    Args:
        ckpt: A checkpoint with `return` conditioning.
        seeds: Number of seeds (0..n-1) or an explicit list.
        steps: Episode length (the environment's own time limit is raised to it).
        conditions: Defaults to `protocol(n_goals, steps)`.
        progress: Show a progress bar.
    """
    import gymnasium as gym

    targets = target_returns(ckpt)
    get_statistic(ckpt.statistic)
    cfg, model = ckpt.config, ckpt.model.eval()
    if cfg.is_image or cfg.discrete_actions:
        raise ValueError(
            "the Decision Transformer baseline is implemented for vector observations and Box actions"
        )
    H = cfg.history_steps  # steps that determine an action
    seed_list = list(range(seeds)) if isinstance(seeds, int) else list(seeds)
    conds = conditions or protocol(len(ckpt.goals), steps)
    runs = [(c, s) for c in conds for s in seed_list]
    n = len(runs)
    envs = [gym.make(ckpt.env_id, max_episode_steps=steps) for _ in runs]
    t0 = time.time()
    first = [env.reset(seed=s)[0] for env, (_, s) in zip(envs, runs, strict=True)]
    D, A = int(cfg.obs_shape[0]), cfg.act_dim
    states = np.zeros((n, steps, D), np.float32)  # normalised
    actions = np.zeros((n, steps, A), np.float32)  # model space [-1, 1]
    rtg = np.zeros((n, steps), np.float32)
    rewards = np.zeros((n, steps), np.float64)
    signal = np.full((n, steps), np.nan)
    terminated = np.zeros(n, dtype=bool)
    alive = np.ones(n, dtype=bool)
    states[:, 0] = ckpt.obs_norm(np.stack(first))
    current = list(first)  # the raw observation each episode acts on (what obs[i] statistics read)
    for t in tqdm(range(steps), disable=not progress, desc="eval dt"):
        idx = np.flatnonzero(alive)
        if len(idx) == 0:
            break
        for i in idx:
            rtg[i, t] = returns_to_go(targets, runs[i][0].goal_at, rewards[i], t)
        lo = max(0, t + 1 - H)
        span = np.arange(lo, t + 1)
        w = pad_left(  # goal ids unused: the returns-to-go go in their place
            [np.zeros(len(span), np.int64) for _ in idx],
            [states[i, lo : t + 1] for i in idx],
            [actions[i, lo : t + 1] for i in idx],
            [span for _ in idx],
            H,
        )
        g = torch.from_numpy(_rtg_window(rtg, idx, lo, t, H))  # [B, H]
        pred, _ = model(g, w.states, w.actions, w.timesteps, w.valid, last_only=True)
        act = pred[:, 0].numpy()  # [B, A] in [-1, 1]
        env_act = ckpt.action_codec.decode(act)
        for j, i in enumerate(idx):
            actions[i, t] = act[j]
            obs, r, term, trunc, info = envs[i].step(env_act[j])
            rewards[i, t] = r
            signal[i, t] = signal_from_step(ckpt.statistic, r, info, current[i], env_act[j])
            current[i] = obs
            if term or trunc:
                terminated[i] = term
                alive[i] = False
            elif t + 1 < steps:
                states[i, t + 1] = ckpt.obs_norm(obs)
    for env in envs:
        env.close()
    return judge(ckpt, conds, seed_list, signal, terminated, "mean (return-to-go)", steps, time.time() - t0)


def _rtg_window(rtg: np.ndarray, idx: np.ndarray, lo: int, t: int, H: int) -> np.ndarray:
    """[B, H] the rows' returns-to-go of steps lo..t, left-padded with zeros (as `pad_left` pads)."""
    out = np.zeros((len(idx), H), np.float32)
    out[:, H - (t + 1 - lo) :] = rtg[idx, lo : t + 1]
    return out
