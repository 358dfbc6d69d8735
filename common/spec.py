"""A served model as both sides describe it: its environment, spaces and goal table.

The clients read it from a server (`GET /models/{name}`, gRPC `GetModel`); evaluation builds one from a checkpoint
to make the same environment a client would (`gmt.common.envs.make_env`).
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class GoalInfo:
    """One row of a model's goal table (statistic of the goal's cluster of training trajectories)."""

    id: int
    name: str
    mean: float
    std: float
    min: float
    max: float
    count: int


@dataclass(frozen=True)
class ModelInfo:
    """A served model: its environment, spaces (as `gmt.common.spaces.space_to_dict` dicts) and goals."""

    name: str
    env_id: str
    observation_space: dict
    action_space: dict
    context_length: int
    statistic: str
    goals: list[GoalInfo] = field(default_factory=list)
    preprocessing: dict | None = None  # the observation pipeline (Atari), None for raw observations
    action_modes: list[str] = field(default_factory=list)  # accepted action modes, the default first
    switch_relabel_steps: int = 0  # past steps a goal change without a blend relabels with the new goal

    def goal(self, id_or_name: int | str) -> GoalInfo:
        """The goal with this id or name.

        Raises:
            KeyError: no such goal.
        """
        for g in self.goals:
            if g.id == id_or_name or g.name == id_or_name:
                return g
        raise KeyError(
            f"model {self.name!r} has no goal {id_or_name!r}; goals: {[g.name for g in self.goals]}"
        )
