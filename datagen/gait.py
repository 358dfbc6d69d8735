"""A scripted Ant gait: joint targets from a phase oscillator, tracked by PD control, heading held by feedback.

Ant's PPO agents here stalled near 0.5 m/s and bounced out of the healthy z-range (docs/results.md, "Ant"). This
gait needs no learning beyond a parameter search (behaviour/ant/TRAINED_WITH.md), never bounces, and changes speed by
changing its stride frequency alone, so every level shares one stride shape and a level started from another
level's state picks up the stride where it is. With a `target_speed` a speed loop sets that frequency every step,
which keeps a level's speed within a few percent over the evaluation protocol's 150-step windows.

Each leg i's hip target is `hip_amp * sin(phase + hip_phase[i]) - yaw_gain * yaw` and its ankle target is
`ankle_sign[i] * (ankle_centre + ankle_amp * sin(phase + hip_phase[i] + ankle_phase[i]))`; the action is
`kp * (target - q) - kd * qdot`, clipped to [-1, 1]. The phase advances by `2 pi freq dt` before each action.
At the start of an episode the phase is 0 from rest, and otherwise the phase whose targets best match the
joints' angles and speeds (`match_phase`), so a pool-started episode does not jerk the legs to a new stride.

A level is saved like any behaviour snapshot (`behaviour.save_behaviour`), of kind `gait`: `<level>.safetensors`
holds the action-noise `log_std` only, and `<level>.json`'s `extra["gait"]` holds a `GaitConfig`; `load_gait`
reads it back (`behaviour.load_behaviour`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np
import torch

from gmt.datagen.behaviour import BehaviourMeta, register_kind, save_behaviour

ENV_ID = "Ant-v5"
# Ant-v5 observation (positions without x, y first): [0] torso z, [1:5] torso quaternion (w, x, y, z),
# [5:13] joint angles (hip_1, ankle_1, hip_2, ankle_2, hip_3, ankle_3, hip_4, ankle_4), [13:19] torso velocity,
# [19:27] joint speeds in the same order.
JOINTS = slice(5, 13)
JOINT_SPEEDS = slice(19, 27)
QUATERNION = slice(1, 5)
X_VELOCITY = 13  # torso x-velocity (world frame)
# Legs 1-4 in observation order -> their (hip, ankle) actuators; Ant-v5's actuators run hip_4, ankle_4, hip_1,
# ankle_1, hip_2, ankle_2, hip_3, ankle_3.
ACTUATORS = ((2, 3), (4, 5), (6, 7), (0, 1))
# Legs 1 and 4 bend their ankles through positive angles, legs 2 and 3 through negative ones.
ANKLE_SIGN = (1.0, -1.0, -1.0, 1.0)
DT = 0.05  # Ant-v5's control step (frame_skip 5 x 0.01 s)
PHASE_GRID = 72  # candidate phases tried by `match_phase`


@dataclass
class GaitConfig:
    """One gait (one speed level).

    Attributes:
        freq: Stride frequency in Hz; the level's speed knob.
        hip_amp: Hip swing amplitude in radians (its sign picks the walking direction).
        ankle_amp: Ankle lift amplitude in radians.
        hip_phase: Per-leg phase offset of the hip swing (legs 1-4), radians.
        ankle_phase: Per-leg phase offset of the ankle lift relative to that leg's hip swing, radians.
        ankle_centre: Mean ankle angle in radians (mirrored per leg by `ANKLE_SIGN`).
        yaw_gain: Hip offset in radians per radian of heading away from +x (steers back to +x).
        kp: Proportional gain, action per radian of joint error.
        kd: Derivative gain, action per rad/s of joint speed.
        rest_speed: Mean absolute joint speed (rad/s) below which an episode counts as starting from rest
            (phase 0); above it the phase is matched to the joints.
        target_speed: With a value (m/s), a speed loop moves the stride frequency every step to hold it:
            `freq + speed_gain * e + integral` clipped to `freq_range`, e = target_speed - smoothed x-velocity,
            the integral summing `speed_ki * e` within +-`integral_limit`. None: the stride runs at `freq`.
        speed_gain: Hz per m/s of speed error.
        speed_ki: Hz per m/s of speed error added to the integral each step.
        speed_alpha: Weight of each step's x-velocity in its exponential smoothing.
        integral_limit: Bound of the integral term (Hz).
        freq_range: The loop's frequency stays within [low, high] Hz.
        ff_slope: Hz per m/s by which a new `GaitPolicy.target` also moves `freq` (feed-forward), so a speed
            asked of one level's policy starts near its stride.
    """

    freq: float
    hip_amp: float
    ankle_amp: float
    hip_phase: list[float] = field(default_factory=lambda: [0.0] * 4)
    ankle_phase: list[float] = field(default_factory=lambda: [0.0] * 4)
    ankle_centre: float = 0.8
    yaw_gain: float = 0.5
    kp: float = 1.0
    kd: float = 0.05
    rest_speed: float = 0.5
    target_speed: float | None = None
    speed_gain: float = 3.0
    speed_ki: float = 0.03
    speed_alpha: float = 0.1
    integral_limit: float = 0.4
    freq_range: tuple[float, float] = (1.0, 2.0)
    ff_slope: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.freq) and self.freq > 0):
            raise ValueError(f"freq must be a positive number of Hz, got {self.freq}")
        if len(self.hip_phase) != 4 or len(self.ankle_phase) != 4:
            raise ValueError("hip_phase and ankle_phase need one entry per leg (4)")
        numbers = [self.hip_amp, self.ankle_amp, self.ankle_centre, self.yaw_gain, self.kp, self.kd]
        if not all(math.isfinite(x) for x in [*numbers, *self.hip_phase, *self.ankle_phase]):
            raise ValueError("gait parameters must be finite")
        self.freq_range = (float(self.freq_range[0]), float(self.freq_range[1]))
        if not 0 < self.freq_range[0] <= self.freq_range[1]:
            raise ValueError(f"freq_range must be 0 < low <= high, got {self.freq_range}")
        if self.target_speed is not None and not math.isfinite(self.target_speed):
            raise ValueError(f"target_speed must be finite, got {self.target_speed}")
        if not 0 < self.speed_alpha <= 1 or self.integral_limit < 0:
            raise ValueError(f"need 0 < speed_alpha <= 1 and integral_limit >= 0, got {self.speed_alpha}, "
                             f"{self.integral_limit}")  # fmt: skip
        if self.kp <= 0 or self.kd < 0 or self.rest_speed < 0:
            raise ValueError(
                f"need kp > 0, kd >= 0, rest_speed >= 0; got {self.kp}, {self.kd}, {self.rest_speed}"
            )

    def with_freq(self, freq: float) -> GaitConfig:
        """The same stride at another frequency."""
        return replace(self, freq=float(freq))


def heading(obs: np.ndarray) -> float:
    """Yaw of the torso (radians, 0 facing +x) from the observation's quaternion."""
    w, x, y, z = (float(v) for v in obs[QUATERNION])
    return math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))


def joint_targets(cfg: GaitConfig, phase: np.ndarray) -> np.ndarray:
    """Joint targets [..., 8] (observation order, without the heading term) at the given phase(s)."""
    phase = np.asarray(phase, dtype=np.float64)[..., None]  # [..., 1]
    hip = cfg.hip_amp * np.sin(phase + np.asarray(cfg.hip_phase))  # [..., 4]
    lift = phase + np.asarray(cfg.hip_phase) + np.asarray(cfg.ankle_phase)  # [..., 4]
    ankle = np.asarray(ANKLE_SIGN) * (cfg.ankle_centre + cfg.ankle_amp * np.sin(lift))
    return np.stack([hip, ankle], axis=-1).reshape(*hip.shape[:-1], 8)  # [..., 4, 2] -> [..., 8]


def match_phase(cfg: GaitConfig, obs: np.ndarray) -> float:
    """The stride phase whose joint targets and their rates best match the observed joints (least squares).

    Angles and speeds are weighed alike once the speeds are divided by the stride's angular frequency.
    """
    grid = np.linspace(0.0, 2 * math.pi, PHASE_GRID, endpoint=False)  # [P]
    omega = 2 * math.pi * cfg.freq
    q = joint_targets(cfg, grid)  # [P, 8]
    eps = 1e-4
    rate = (joint_targets(cfg, grid + eps) - joint_targets(cfg, grid - eps)) / (2 * eps)  # [P, 8], d/dphase
    err = ((q - obs[JOINTS]) ** 2).sum(-1) + ((rate - obs[JOINT_SPEEDS] / omega) ** 2).sum(-1)  # [P]
    return float(grid[int(np.argmin(err))])


class GaitPolicy:
    """One gait level as a behaviour policy: `act(obs, rng)`, `start_episode()`, `noise_scale`, `meta`.

    Args:
        meta: The snapshot's metadata; `meta.extra["gait"]` is the `GaitConfig` as a dict.
        log_std: Per-action log standard deviation of the Gaussian noise added by `act` when given an `rng`.
        low: Action-space lower bounds.
        high: Action-space upper bounds.
    """

    def __init__(self, meta: BehaviourMeta, log_std: np.ndarray, low: np.ndarray, high: np.ndarray):
        self.meta = meta
        self.cfg = GaitConfig(**meta.extra["gait"])
        self.log_std = np.asarray(log_std, dtype=np.float64)
        self.low = np.asarray(low, dtype=np.float32)
        self.high = np.asarray(high, dtype=np.float32)
        self.noise_scale = 1.0  # multiplies the noise std of `act`
        self.phase: float | None = None
        self.speed: float | None = None  # smoothed x-velocity (speed loop)
        self.integral = 0.0  # the speed loop's integral term (Hz)
        self.freq = self.cfg.freq  # the stride frequency of the last action

    @property
    def command(self) -> float:
        """The level's command: its target speed (m/s) with a speed loop, else its stride frequency (Hz)."""
        return self.cfg.freq if self.cfg.target_speed is None else self.cfg.target_speed

    @command.setter
    def command(self, value: float) -> None:
        if self.cfg.target_speed is None:
            self.cfg = self.cfg.with_freq(value)
        else:
            shift = self.cfg.ff_slope * (float(value) - self.cfg.target_speed)
            self.cfg = replace(self.cfg, target_speed=float(value), freq=self.cfg.freq + shift)

    target = command  # as for `BehaviourPolicy`: the value a level is asked to hold

    def start_episode(self) -> None:
        """Forget the phase and the speed loop's state; the next action picks the phase from the observation."""
        self.phase = None
        self.speed = None
        self.integral = 0.0

    def stride_freq(self, obs: np.ndarray) -> float:
        """This step's stride frequency: `freq`, or the speed loop's (advances its smoothing and integral)."""
        cfg = self.cfg
        if cfg.target_speed is None:
            return cfg.freq
        vx = float(obs[X_VELOCITY])
        self.speed = vx if self.speed is None else (1 - cfg.speed_alpha) * self.speed + cfg.speed_alpha * vx
        error = cfg.target_speed - self.speed
        self.integral = float(
            np.clip(self.integral + cfg.speed_ki * error, -cfg.integral_limit, cfg.integral_limit)
        )
        return float(np.clip(cfg.freq + cfg.speed_gain * error + self.integral, *cfg.freq_range))

    def act(self, obs: np.ndarray, rng: np.random.Generator | None = None) -> np.ndarray:
        """The PD action towards the next phase's joint targets, plus Gaussian noise when `rng` is given."""
        obs = np.asarray(obs, dtype=np.float64)
        if self.phase is None:
            moving = np.abs(obs[JOINT_SPEEDS]).mean() > self.cfg.rest_speed
            self.phase = match_phase(self.cfg, obs) if moving else 0.0
        self.freq = self.stride_freq(obs)
        self.phase = (self.phase + 2 * math.pi * self.freq * DT) % (2 * math.pi)
        target = joint_targets(self.cfg, self.phase)  # [8]
        target[0::2] -= self.cfg.yaw_gain * heading(obs)
        torque = (
            self.cfg.kp * (target - obs[JOINTS]) - self.cfg.kd * obs[JOINT_SPEEDS]
        )  # [8], observation order
        action = np.empty(8)
        for leg, (hip, ankle) in enumerate(ACTUATORS):
            action[hip], action[ankle] = torque[2 * leg], torque[2 * leg + 1]
        if rng is not None:
            action = action + np.exp(self.log_std) * self.noise_scale * rng.standard_normal(8)
        return np.clip(action, self.low, self.high).astype(np.float32)


def gait_meta(level: str, cfg: GaitConfig, **measured) -> BehaviourMeta:
    """Snapshot metadata for one gait level (no network, no observation normalisation)."""
    return BehaviourMeta(
        env_id=ENV_ID,
        level=level,
        hidden_sizes=[],
        activation="tanh",
        obs_mean=[],
        obs_var=[],
        extra={"gait": asdict(cfg), **measured.pop("extra", {})},
        kind="gait",
        **measured,
    )


@register_kind("gait")
def load_gait(path, meta: BehaviourMeta, state: dict[str, torch.Tensor], action_space) -> GaitPolicy:
    """A `GaitPolicy` from a gait snapshot: its only tensor is the action noise's `log_std`."""
    if set(state) != {"log_std"}:
        raise ValueError(f"{path}.safetensors: a gait snapshot holds log_std only, got {sorted(state)}")
    return GaitPolicy(meta, state["log_std"].numpy(), action_space.low, action_space.high)


def gait_state(noise_std: float) -> dict[str, torch.Tensor]:
    """The snapshot's tensors: the action noise as `log_std` [8]."""
    if not noise_std > 0:
        raise ValueError(f"noise_std must be > 0, got {noise_std}")
    return {"log_std": torch.full((8,), math.log(noise_std))}


def write_levels(
    cfg: GaitConfig,
    freqs: dict[str, float],
    noise_std: float,
    out_dir,
    command: str,
    episodes: int = 10,
    seed: int = 20_000,
    max_steps: int | None = None,
    targets: dict[str, float] | None = None,
) -> list:
    """Measure and write one gait snapshot per level (`<out_dir>/<level>.safetensors/.json`) and TRAINED_WITH.md.

    Args:
        cfg: The stride; each level takes it at its own frequency.
        freqs: Level name -> stride frequency (Hz).
        noise_std: Std of the Gaussian action noise (the snapshot's log_std).
        out_dir: The environment's behaviour folder, e.g. behaviour/ant.
        command: The command line that wrote them, for the provenance file.
        episodes: Noisy episodes measured per level.
        seed: First reset seed of the measurement.
        max_steps: Optional cap on episode length (tests use a tiny one).
        targets: Level -> target speed (m/s) held by the speed loop (`GaitConfig.target_speed`); levels not
            named run open-loop at their frequency.

    Returns:
        The written paths.
    """
    from pathlib import Path

    import gymnasium as gym

    from gmt.datagen.rollout import measure

    if not freqs:
        raise ValueError("name at least one level")
    targets = dict(targets or {})
    if set(targets) - set(freqs):
        raise ValueError(f"targets name levels without a frequency: {sorted(set(targets) - set(freqs))}")
    out_dir = Path(out_dir)
    env = gym.make(ENV_ID)
    state = gait_state(noise_std)
    rows, written = [], []
    for level, freq in freqs.items():
        level_cfg = replace(cfg, freq=float(freq), target_speed=targets.get(level))
        policy = GaitPolicy(gait_meta(level, level_cfg), state["log_std"].numpy(), env.action_space.low,
                            env.action_space.high)  # fmt: skip
        m = measure(env, policy, episodes, seed, max_steps)
        meta = gait_meta(level, level_cfg, mean_speed=m["mean_speed"], std_speed=m["std_speed"],
                         extra={"episodes": episodes, "falls": m["falls"], "mean_length": m["mean_length"]})  # fmt: skip
        save_behaviour(out_dir / level, state, meta)
        written.append(out_dir / f"{level}.json")
        target = "open loop" if level not in targets else f"{targets[level]:g}"
        rows.append(
            f"| {level} | {freq:g} | {target} | {m['mean_speed']:.3f} | {m['std_speed']:.3f} | {m['falls']} | {m['mean_length']:.0f} |"
        )
    text = [
        f"# Scripted gait levels for {ENV_ID}",
        "",
        "Written (and measured) with:",
        "",
        "```bash",
        command,
        "```",
        "",
        "Each level is `gmt.datagen.gait.GaitPolicy`: one stride (a phase oscillator's joint targets tracked by PD "
        "control, heading held by feedback) at its own frequency, with Gaussian action noise of std "
        f"{noise_std:g}. Speeds are the mean and standard deviation over {episodes} noisy episodes (reset seeds "
        f"{seed}+) of the per-episode mean `x_velocity` (m/s).",
        "",
        "| level | stride Hz | loop target m/s | mean speed | std | falls | mean length |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        *rows,
        "",
    ]
    provenance = out_dir / "TRAINED_WITH.md"
    if provenance.exists() and "\n## Notes" in (old := provenance.read_text()):  # keep notes added by hand
        text.append(old[old.index("\n## Notes") + 1 :].rstrip("\n") + "\n")
    provenance.write_text("\n".join(text))
    return [*written, out_dir / "TRAINED_WITH.md"]
