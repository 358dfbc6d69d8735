"""The models a server answers for: one loaded checkpoint and one `PolicyEngine` per model name."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

from gmt.model.checkpoint import META, Checkpoint, CheckpointError, load_checkpoint
from gmt.model.engine import PolicyEngine
from gmt.service.errors import InvalidArgument, NotFound, Unavailable

log = logging.getLogger("gmt.registry")


def discover(paths: list[Path]) -> list[Path]:
    """Checkpoint directories among `paths`: each path itself if it holds gmt.json, else its sub-directories that do."""
    found: list[Path] = []
    for p in paths:
        if (p / META).is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(d for d in p.iterdir() if d.is_dir() and (d / META).is_file()))
    return found


def engine_for(checkpoint: Checkpoint, naive: bool = False) -> PolicyEngine:
    """The engine serving a checkpoint: incremental for `window` models, the reference recompute otherwise or when
    `naive`."""
    return PolicyEngine(checkpoint, incremental=False if naive else None)


@dataclass
class LoadedModel:
    """A checkpoint ready to serve.

    Attributes:
        name: Model name clients use (the checkpoint directory's name).
        path: Checkpoint directory.
        checkpoint: The loaded checkpoint.
        engine: The engine answering its acts (incremental for `window` models, recompute otherwise).
    """

    name: str
    path: Path
    checkpoint: Checkpoint
    engine: PolicyEngine


@dataclass
class ModelRegistry:
    """Loaded models by name, plus the errors of those that failed to load."""

    models: dict[str, LoadedModel] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)

    @classmethod
    def load(cls, paths: list[Path], naive: bool = False) -> ModelRegistry:
        """Load every checkpoint found under `paths`; a broken one is logged and skipped.

        `naive` serves every model by the reference recompute (the exactness oracle and benchmark baseline).
        """
        reg = cls()
        for d in discover(paths):
            name = d.name
            if name in reg.models:
                reg.errors[str(d)] = (
                    f"duplicate model name {name!r} (already loaded from {reg.models[name].path})"
                )
                log.error("checkpoint skipped", extra={"path": str(d), "error": reg.errors[str(d)]})
                continue
            try:
                ckpt = load_checkpoint(d, name=name)
            except (CheckpointError, KeyError, TypeError, ValueError, OSError) as e:
                reg.errors[str(d)] = str(e)
                log.error("checkpoint failed to load", extra={"path": str(d), "error": str(e)})
                continue
            engine = engine_for(ckpt, naive)
            reg.models[name] = LoadedModel(name, d, ckpt, engine)
            log.info(
                "model loaded",
                extra={
                    "model": name,
                    "path": str(d),
                    "env_id": ckpt.env_id,
                    "goals": len(ckpt.goals),
                    "attention": ckpt.config.attention,
                    "engine": engine.describe().path,
                    "kernel": engine.describe().kernel,
                },
            )
        return reg

    @classmethod
    def of(cls, *checkpoints: Checkpoint, naive: bool = False) -> ModelRegistry:
        """A registry of already-loaded checkpoints (tests, notebooks)."""
        reg = cls()
        for c in checkpoints:
            reg.models[c.name] = LoadedModel(c.name, Path("."), c, engine_for(c, naive))
        return reg

    def get(self, name: str) -> LoadedModel:
        """The model called `name`.

        Raises:
            NotFound: no such model.
        """
        try:
            return self.models[name]
        except KeyError:
            raise NotFound(f"unknown model {name!r}; loaded models: {self._names()}") from None

    def resolve(self, name: str | None) -> LoadedModel:
        """The model called `name`, or the only loaded model when `name` is empty.

        Raises:
            InvalidArgument: no name given while several models are loaded.
            NotFound: no such model.
            Unavailable: no model is loaded at all.
        """
        if not self.models:
            raise Unavailable("no model is loaded on this server")
        if name:
            return self.get(name)
        if len(self.models) == 1:
            return next(iter(self.models.values()))
        raise InvalidArgument(f"model is required: loaded models are {self._names()}")

    def _names(self) -> str:
        return ", ".join(sorted(self.models)) or "(none)"
