"""Local environments for a served model: made and preprocessed according to the model's spec.

`make_env` picks a maker by the spec (Atari ids get the usual DQN preprocessing sized to the spec's observation
space; everything else is a plain `gym.make`), then `check_spaces` refuses an environment whose spaces differ
from the model's.
"""

from __future__ import annotations

import os
from collections.abc import Callable

import gymnasium as gym

from gmt.common.extras import MissingExtra, require_module
from gmt.common.spec import ModelInfo

VIDEO_SIZE = (480, 320)  # width, height of rendered MuJoCo frames
# The camera that follows the agent's centre of mass (`mode="trackcom"`) in the MJCF of Gymnasium's HalfCheetah,
# Hopper, Walker2d and Ant. Without a camera named, Gymnasium renders from a free camera that stays put, and the
# agent runs out of the picture.
TRACKING_CAMERA = "track"


class SpaceMismatch(ValueError):
    """The local environment's spaces are not the model's."""


def describe_space(d: dict) -> str:
    """A short text for a space dict, e.g. "Box(float64, shape=[17])" or "Discrete(6)"."""
    if d["type"] == "discrete":
        return f"Discrete({d['n']})"
    return f"Box({d.get('dtype', '?')}, shape={list(d.get('shape', []))})"


def is_atari(env_id: str) -> bool:
    """Whether `env_id` is an Arcade Learning Environment game."""
    return env_id.startswith("ALE/")


def _make_atari(spec: ModelInfo, env_id: str, max_steps: int | None, render: bool) -> gym.Env:
    """ALE game with DQN preprocessing (frame skip 4, grayscale, square resize, stacking) matching the spec.

    The raw game is returned unchanged when the spec describes raw frames. The arguments come from the spec's
    `preprocessing` (what the model's training data declared); a spec without one gets the defaults of
    `atari_env`, sized by its observation shape. Preprocessing uses Gymnasium's `AtariPreprocessing` (OpenCV).
    Both come with the `atari` extra.
    """
    require_module("ale_py", "atari", f"environment {env_id}")
    require_module("cv2", "atari", f"environment {env_id}")
    import ale_py

    gym.register_envs(ale_py)
    kw = {"render_mode": "rgb_array"} if render else {}
    shape = list(spec.observation_space.get("shape", []))
    raw = gym.make(env_id, max_episode_steps=max_steps, **kw)
    if list(raw.observation_space.shape) == shape:
        return raw
    raw.close()
    p = spec.preprocessing or {}
    size = int(p.get("screen_size", shape[-1] if shape else 84))
    stack = int(p.get("stack", shape[0] if len(shape) == 3 else 0))
    args = {k: p[k] for k in ("frame_skip", "noop_max", "repeat_action_probability") if k in p}
    env = atari_env(env_id, size, stack, **args, **kw)
    # The limit counts agent steps: on the raw game it would count frames, reset's no-ops included.
    return gym.wrappers.TimeLimit(env, max_steps) if max_steps else env


def atari_env(
    env_id: str,
    screen_size: int,
    stack: int = 0,
    frame_skip: int = 4,
    noop_max: int = 30,
    repeat_action_probability: float = 0.25,
    **make_kwargs,
) -> gym.Env:
    """An ALE game with the DQN preprocessing the project's Atari data and clients share (one definition).

    `gym.make(env_id, frameskip=1, repeat_action_probability)` -> `AtariPreprocessing` (max-pool of the last two
    frames, grayscale, INTER_AREA resize to `screen_size`, up to `noop_max` no-ops after reset, no terminal on a
    lost life) -> `FrameStackObservation(stack)` when `stack` > 0. Observations: uint8 [stack, H, W] or [H, W].
    """
    env = gym.make(env_id, frameskip=1, repeat_action_probability=repeat_action_probability, **make_kwargs)
    env = gym.wrappers.AtariPreprocessing(
        env,
        noop_max=noop_max,
        frame_skip=frame_skip,
        screen_size=screen_size,
        grayscale_obs=True,
        terminal_on_life_loss=False,
        scale_obs=False,
    )
    return gym.wrappers.FrameStackObservation(env, stack_size=stack) if stack else env


def _make_plain(spec: ModelInfo, env_id: str, max_steps: int | None, render: bool) -> gym.Env:
    """`gym.make(env_id)`; MuJoCo frames are rendered offscreen (EGL unless MUJOCO_GL says otherwise) by the
    model's tracking camera (`TRACKING_CAMERA`; a model without one falls back to Gymnasium's free camera).

    Raises:
        MissingExtra: a MuJoCo environment without MuJoCo installed (the `run` extra).
    """
    try:
        return _gym_make(env_id, max_steps, render)
    except gym.error.DependencyNotInstalled as e:
        if "mujoco" not in str(e).lower():
            raise
        raise MissingExtra("run", f"environment {env_id}", ["mujoco"]) from None


def _gym_make(env_id: str, max_steps: int | None, render: bool) -> gym.Env:
    if not render:
        return gym.make(env_id, max_episode_steps=max_steps)
    os.environ.setdefault("MUJOCO_GL", "egl")
    width, height = VIDEO_SIZE
    try:
        return gym.make(
            env_id,
            max_episode_steps=max_steps,
            render_mode="rgb_array",
            width=width,
            height=height,
            camera_name=TRACKING_CAMERA,
        )
    except TypeError:  # not a MuJoCo env: no width / height / camera arguments
        return gym.make(env_id, max_episode_steps=max_steps, render_mode="rgb_array")


EnvMaker = Callable[[ModelInfo, str, "int | None", bool], gym.Env]
MAKERS: list[tuple[Callable[[str], bool], EnvMaker]] = [(is_atari, _make_atari)]


# MuJoCo warnings known to be noise: Gymnasium's v5 model files still use a compiler attribute MuJoCo 3.3+ deprecates
# (printed by MuJoCo's C code on every environment made, and appended to MUJOCO_LOG.TXT).
KNOWN_MUJOCO_NOISE = ("compiler attribute 'settotalmass' is deprecated",)


def quiet_known_mujoco_warnings() -> None:
    """Route MuJoCo's warnings through Python's `warnings` (MuJoCo's `mju_user_warning` callback), dropping
    `KNOWN_MUJOCO_NOISE`; a callback someone else installed is left alone. No-op without MuJoCo."""
    try:
        import mujoco
    except ImportError:
        return
    if mujoco.get_mju_user_warning() is not None:
        return

    def on_warning(message: str) -> None:
        if not any(noise in message for noise in KNOWN_MUJOCO_NOISE):
            import warnings

            warnings.warn(f"MuJoCo: {message}", RuntimeWarning, stacklevel=2)

    mujoco.set_mju_user_warning(on_warning)


def make_env(
    spec: ModelInfo, env_id: str | None = None, max_steps: int | None = None, render: bool = False
) -> gym.Env:
    """The environment to drive with `spec`'s model (default id: the model's own), time limit `max_steps`.

    Raises:
        SpaceMismatch: its spaces are not the model's.
    """
    env_id = env_id or spec.env_id
    quiet_known_mujoco_warnings()
    maker = next((m for pred, m in MAKERS if pred(env_id)), _make_plain)
    env = maker(spec, env_id, max_steps, render)
    try:
        check_spaces(spec, env, env_id)
    except SpaceMismatch:
        env.close()
        raise
    return env


def check_spaces(spec: ModelInfo, env: gym.Env, env_id: str) -> None:
    """Raise `SpaceMismatch`, naming both sides, when `env`'s spaces differ from the model's."""
    from gmt.common.spaces import space_to_dict, spaces_match

    problems = []
    for what, model_space, env_space in (
        ("observation", spec.observation_space, env.observation_space),
        ("action", spec.action_space, env.action_space),
    ):
        local = space_to_dict(env_space)
        if not spaces_match(local, model_space):
            problems.append(
                f"{what} space {describe_space(local)} of {env_id} vs {describe_space(model_space)} of the model"
            )
    if problems:
        raise SpaceMismatch(
            f"environment {env_id} does not match model {spec.name!r} (trained on {spec.env_id}): "
            + "; ".join(problems)
        )
