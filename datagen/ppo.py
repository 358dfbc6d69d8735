"""The one PPO trainer of the data lab: Stable-Baselines3 PPO built from a preset, run with a measured snapshot
every so many steps, and its actor moved to and from `BehaviourPolicy` snapshots.

Its three uses are configurations over it, each with its own reward, measurement and choice of snapshot:
`train_behaviour` (speed levels, `gmt data behaviour`), `train_commanded` (one speed-commanded actor,
`gmt data commanded`) and `refine_behaviour` (one level fine-tuned from other levels' states, `gmt data refine`);
`ppo_state` saves and resumes a whole learner. Needs the optional `train` extra.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from importlib.metadata import version
from pathlib import Path

import torch

from gmt.datagen.behaviour import BehaviourMeta, BehaviourPolicy


@dataclass
class PPOPreset:
    """PPO hyperparameters (rl-zoo style) for one environment.

    `stuck_penalty` > 0 wraps the training env in `StuckTermination` (training only; collection and
    measurements use the plain environment).
    """

    n_steps: int = 512
    batch_size: int = 64
    n_epochs: int = 10
    learning_rate: float = 3e-4
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_range: float = 0.2
    ent_coef: float = 0.0
    vf_coef: float = 0.5
    max_grad_norm: float = 0.5
    hidden_sizes: list[int] = field(default_factory=lambda: [256, 256])
    activation: str = "relu"
    log_std_init: float = -2.0
    ortho_init: bool = False
    stuck_penalty: float = 0.0


PRESETS: dict[str, PPOPreset] = {
    # rl-zoo's tuned HalfCheetah settings.
    "halfcheetah": PPOPreset(
        n_steps=512, batch_size=64, n_epochs=20, learning_rate=2.0633e-05, gamma=0.98, gae_lambda=0.92,
        clip_range=0.1, ent_coef=0.000401762, vf_coef=0.58096, max_grad_norm=0.8, stuck_penalty=200.0,
    ),
    # SB3's default PPO: its unit initial noise keeps Hopper and Walker2d from settling on standing still
    # for the healthy reward (rl-zoo's Hopper settings with log-std -2 did, for 460k steps).
    "hopper": PPOPreset(n_steps=2048, hidden_sizes=[64, 64], activation="tanh", log_std_init=0.0, ortho_init=True),
    "walker2d": PPOPreset(n_steps=2048, hidden_sizes=[64, 64], activation="tanh", log_std_init=0.0, ortho_init=True),
    # Ant: with unit noise the control cost (0.5 |a|^2, about 2 per step) outweighs the healthy reward (1 per
    # step), so default PPO learnt to flip over early; a tenth of the cost in training left it flailing in
    # place. A smaller initial noise (std 0.37, cost about 0.5 per step) keeps staying up worthwhile.
    "ant": PPOPreset(n_steps=2048, hidden_sizes=[64, 64], activation="tanh", log_std_init=-1.0, ortho_init=True),
}  # fmt: skip


def actor_linears(policy) -> list[torch.nn.Linear]:
    """The Linear layers of an SB3 actor's mean network, in order (they map to `mean_net.0, .2, ...`)."""
    linears = [m for m in policy.mlp_extractor.policy_net if isinstance(m, torch.nn.Linear)]
    return [*linears, policy.action_net]


def actor_state(policy) -> dict[str, torch.Tensor]:
    """An SB3 actor's weights under `BehaviourPolicy`'s names: mean network and log-std."""
    state = {}
    for i, lin in enumerate(actor_linears(policy)):
        state[f"mean_net.{2 * i}.weight"] = lin.weight.detach().cpu().clone()
        state[f"mean_net.{2 * i}.bias"] = lin.bias.detach().cpu().clone()
    state["log_std"] = policy.log_std.detach().cpu().clone()
    return state


def export_actor(model, vec_normalize, env_id: str, level: str, hidden_sizes: list[int], activation: str):
    """The SB3 PPO actor as (state dict, meta): mean network, log-std, observation normalisation."""
    state = actor_state(model.policy)
    rms = vec_normalize.obs_rms
    meta = BehaviourMeta(
        env_id=env_id,
        level=level,
        hidden_sizes=list(hidden_sizes),
        activation=activation,
        obs_mean=[float(x) for x in rms.mean],
        obs_var=[float(x) for x in rms.var],
        obs_clip=float(vec_normalize.clip_obs),
        obs_epsilon=float(vec_normalize.epsilon),
    )
    return state, meta


def as_policy(state: dict, meta: BehaviourMeta, action_space) -> BehaviourPolicy:
    """Build the torch-only behaviour policy from an exported state dict."""
    policy = BehaviourPolicy(
        meta, len(meta.obs_mean), action_space.shape[0], action_space.low, action_space.high
    )
    policy.load_state_dict(state, strict=False)
    return policy.eval()


def make_ppo(make_env, p: PPOPreset, seed: int, norm_obs: bool = True):
    """An SB3 PPO learner with preset `p`, on the CPU, over one env from `make_env`; its rewards are normalised,
    and its observations too unless `norm_obs` is False (an env that normalises them itself).

    Returns:
        The learner and its `VecNormalize` env (whose statistics a snapshot exports).
    """
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    venv = VecNormalize(DummyVecEnv([make_env]), norm_obs=norm_obs, gamma=p.gamma)
    venv.seed(seed)
    act = {"relu": torch.nn.ReLU, "tanh": torch.nn.Tanh}[p.activation]
    model = PPO(
        "MlpPolicy",
        venv,
        n_steps=p.n_steps,
        batch_size=p.batch_size,
        n_epochs=p.n_epochs,
        learning_rate=p.learning_rate,
        gamma=p.gamma,
        gae_lambda=p.gae_lambda,
        clip_range=p.clip_range,
        ent_coef=p.ent_coef,
        vf_coef=p.vf_coef,
        max_grad_norm=p.max_grad_norm,
        policy_kwargs=dict(
            log_std_init=p.log_std_init,
            ortho_init=p.ortho_init,
            activation_fn=act,
            net_arch=dict(pi=list(p.hidden_sizes), vf=list(p.hidden_sizes)),
        ),
        seed=seed,
        device="cpu",
        verbose=0,
    )
    return model, venv


def snapshot_path(work_dir: Path, step: int) -> Path:
    """Where the actor snapshot of training step `step` is kept (without suffix)."""
    return Path(work_dir) / f"step_{step:08d}"


def level_state(policy: BehaviourPolicy) -> dict[str, torch.Tensor]:
    """A snapshot's tensors as a level file keeps them (the observation statistics live in its JSON)."""
    return {k: v for k, v in policy.state_dict().items() if k not in ("obs_mean", "obs_var")}


def copy_actor(policy, state: dict[str, torch.Tensor], source: str = "the snapshot") -> None:
    """Load a `BehaviourPolicy` state (mean network and log-std) into an SB3 actor of the same layer sizes.

    Raises:
        ValueError: A layer of `state` differs in shape from the actor's.
    """
    with torch.no_grad():
        for i, lin in enumerate(actor_linears(policy)):
            weight, bias = state[f"mean_net.{2 * i}.weight"], state[f"mean_net.{2 * i}.bias"]
            if weight.shape != lin.weight.shape:
                raise ValueError(
                    f"{source}: layer {i} is {tuple(weight.shape)}, this learner's {tuple(lin.weight.shape)}"
                )
            lin.weight.copy_(weight)
            lin.bias.copy_(bias)
        policy.log_std.copy_(state["log_std"])


def run_ppo(
    model,
    timesteps: int,
    every: Callable[[int], int],
    measure: Callable[[int], dict],
    records: list[dict],
    work_dir: Path,
    on_step: Callable[[int], None] | None = None,
    reset_num_timesteps: bool = True,
) -> list[dict]:
    """Train `model` for `timesteps` more steps; at every step `every(step)` divides, measure a snapshot.

    Args:
        model: The learner (`make_ppo`).
        timesteps: Environment steps to train for.
        every: Step -> the snapshot interval in force there.
        measure: Step -> that step's snapshot measurement (it exports and measures the actor, and prints).
        records: The measurements so far; each new one is appended and the list written to
            `<work_dir>/records.json`.
        work_dir: Where the run keeps its snapshots and measurements.
        on_step: Called with the step count after every environment step, before a snapshot (e.g. to unfreeze
            the actor after a critic warm-up).
        reset_num_timesteps: False when the learner goes on from a loaded step (`ppo_state`).

    Returns:
        `records`.
    """
    from stable_baselines3.common.callbacks import BaseCallback

    class Snapshots(BaseCallback):
        def _on_step(self) -> bool:
            step = self.num_timesteps
            if on_step is not None:
                on_step(step)
            if step % every(step) == 0:
                keep_record(records, measure(step), work_dir)
            return True

    model.learn(total_timesteps=timesteps, callback=Snapshots(), reset_num_timesteps=reset_num_timesteps)
    return records


def keep_record(records: list[dict], record: dict, work_dir: Path) -> None:
    """Append a snapshot's measurement and write every one so far to `<work_dir>/records.json`."""
    records.append(record)
    (Path(work_dir) / "records.json").write_text(json.dumps(records, indent=1))


def trained_with(title: str, command: str, preset: PPOPreset) -> str:
    """The head of a TRAINED_WITH.md: its title, the command, the package versions and the PPO preset."""
    pkgs = ", ".join(f"{p} {version(p)}" for p in ("stable-baselines3", "torch", "gymnasium", "mujoco"))
    return f"""# {title}

Trained and chosen with (single process, `torch.set_num_threads(1)`, CPU):

```bash
{command}
```

Packages: {pkgs}. PPO hyperparameters: `{asdict(preset)}`.
"""
