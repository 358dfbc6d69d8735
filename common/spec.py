"""The records both sides share, defined once: a goal, a served model and a session.

The clients read them from a server (`GET /models/{name}`, gRPC `GetModel`, a session's answers); evaluation builds
a `ModelInfo` from a checkpoint to make the same environment a client would (`gmt.common.envs.make_env`). The server
answers the same dataclasses (`gmt.service.views`), the REST schemas are built from their fields
(`gmt.service.rest.schemas`), the gRPC converters copy them field by field (`gmt.service.grpc.convert`), and
tests/common/test_spec.py checks that the proto messages carry every field under the same name.

Each field's one-line description is its `doc` metadata; a field with `optional` metadata may be left out of an
answer (its default stands in), every other one is always sent.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields


def doc(text: str, *, optional: bool = False) -> dict:
    """A record field's metadata: its one-line description, and whether an answer may leave it out."""
    return {"doc": text, "optional": optional}


def field_docs(record: type) -> dict[str, str]:
    """Each field of a record dataclass and its one-line description."""
    return {f.name: f.metadata.get("doc", "") for f in fields(record)}


@dataclass(frozen=True)
class GoalInfo:
    """One row of a model's goal table (statistic of the goal's cluster of training trajectories)."""

    id: int = field(metadata=doc("The goal's id: its token, 0 for the lowest statistic."))
    name: str = field(metadata=doc("The goal's name."))
    mean: float = field(metadata=doc("Mean statistic of the goal's trajectories."))
    std: float = field(metadata=doc("Standard deviation of the statistic of the goal's trajectories."))
    min: float = field(metadata=doc("Smallest statistic of the goal's trajectories."))
    max: float = field(metadata=doc("Largest statistic of the goal's trajectories."))
    count: int = field(metadata=doc("How many training trajectories the goal's cluster holds."))


@dataclass(frozen=True)
class ModelInfo:
    """A served model: its environment, spaces (as `gmt.common.spaces.space_to_dict` dicts) and goals."""

    name: str = field(metadata=doc("The model's name."))
    env_id: str = field(metadata=doc("The Gymnasium environment id the model acts in."))
    observation_space: dict = field(metadata=doc("The environment's observation space."))
    action_space: dict = field(metadata=doc("The environment's action space."))
    context_length: int = field(metadata=doc("K: the most past steps the model attends to."))
    statistic: str = field(
        metadata=doc(
            "The per-trajectory statistic the goals cluster, as a client measures it: an expression "
            "AGG(SOURCE) such as mean(info.x_velocity) or mean(abs(obs[2])), a name (return), or a module:function "
            "plug-in (docs/your-own-data.md)."
        )
    )
    goals: list[GoalInfo] = field(
        default_factory=list, metadata=doc("The goal table, goal 0 = lowest statistic.")
    )
    preprocessing: dict | None = field(
        default=None,
        metadata=doc(
            "The observation pipeline of the training data (Atari: Gymnasium wrappers and their "
            "arguments), to reproduce observations client-side; null for raw environment observations.",
            optional=True,
        ),
    )
    action_modes: list[str] = field(
        default_factory=list, metadata=doc("Accepted `action_mode` values; the first is the default.")
    )
    switch_relabel_steps: int = field(
        default=0,
        metadata=doc(
            "On a goal change without a blend, this many past steps of the session's context take the "
            "new goal token, as if it had been pursued all along (0: the context keeps its goals).",
            optional=True,
        ),
    )

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


@dataclass(frozen=True)
class SessionInfo:
    """A session's state, as the server answers it (the defaults serve clients that build one by hand)."""

    session_id: str = field(metadata=doc("The session's id."))
    model: str = field(metadata=doc("The model the session runs."))
    goal: int = field(metadata=doc("The goal the session pursues (the target of a running blend)."))
    goal_name: str = field(default="", metadata=doc("The name of `goal`."))
    step: int = field(default=0, metadata=doc("The step of the next observation (0 after create or reset)."))
    context_size: int = field(default=0, metadata=doc("Steps in the session's context."))
    blend_remaining: int = field(default=0, metadata=doc("Steps left of a running blend (0: none runs)."))
    blend_from: int = field(
        default=0, metadata=doc("The goal being faded out (equal to `goal` when no blend runs).")
    )
    idle_timeout_s: float = field(default=0.0, metadata=doc("Seconds without a call after which it ends."))
    expires_in_s: float = field(
        default=0.0, metadata=doc("Seconds left before the idle timeout ends the session.")
    )
    action_mode: str = field(
        default="", metadata=doc("How actions are chosen (argmax, sample, expert or mean).")
    )
    context_goals: tuple[int, ...] = field(
        default=(), metadata=doc("Goal token of each step in the context, oldest first.")
    )
    model_version: str = field(
        default="", metadata=doc("The model version the session runs for its whole life.")
    )
    recording: bool = field(
        default=False, metadata=doc("Whether the session records its episode.", optional=True)
    )
    effective_step: int | None = field(
        default=None,
        metadata=doc(
            "In the answer to a goal change: the step of the first act that uses the new goal.", optional=True
        ),
    )
