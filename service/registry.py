"""The models a server answers for: per model name, its loaded versions (one checkpoint and one `PolicyEngine`
each), the default version new sessions get, and an optional canary that gets a share of them.

A version is `Checkpoint.version` (gmt.json's `version`, else the fingerprint's first 12 hex digits). A version is
`serving` (new sessions may name it) or `draining` (it serves its sessions only, and the core unloads it once this
server holds none). The registry only keeps the table; the core loads, starts and stops what it names.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path

from gmt.model import native as native_kernel
from gmt.model.checkpoint import (
    META,
    WEIGHTS,
    Checkpoint,
    CheckpointError,
    fingerprint,
    load_checkpoint,
    read_meta,
    version_of,
)
from gmt.model.engine import PolicyEngine, resolve_device
from gmt.service.errors import AlreadyExists, FailedPrecondition, InvalidArgument, NotFound, Unavailable

log = logging.getLogger("gmt.registry")
SERVING, DRAINING = "serving", "draining"
MEMORY_VERSION = "memory"  # the version of a checkpoint built in memory (it has no fingerprint)
SCAN_DEPTH = 2  # how deep under a checkpoint root `find` looks for checkpoint directories


def model_key(name: str, version: str) -> str:
    """The one spelling of (model name, version) in batchers, stores and logs: `name@version`."""
    return f"{name}@{version}"


def discover(paths: list[Path]) -> list[Path]:
    """Checkpoint directories among `paths`: each path itself if it holds gmt.json, else its sub-directories that do."""
    found: list[Path] = []
    for p in paths:
        if (p / META).is_file():
            found.append(p)
        elif p.is_dir():
            found.extend(sorted(d for d in p.iterdir() if d.is_dir() and (d / META).is_file()))
    return found


def engine_for(
    checkpoint: Checkpoint,
    naive: bool = False,
    device: str = "cpu",
    n_slots: int = 16,
    precision: str = "fp32",
) -> PolicyEngine:
    """The engine serving a checkpoint: incremental for `window` models, the reference recompute otherwise or when
    `naive`; on `device` (`PolicyEngine`), whose session pool is allocated for `n_slots` sessions up front when it
    is not the CPU, and warmed up there (one throwaway act) so that no session's first act pays the device's start;
    with the native step's `precision` (fp32 for the naive server, whose recompute is the exactness oracle, and for
    models the native step does not serve: image or full-attention models, or off the CPU; logged)."""
    on_cpu = resolve_device(device) == "cpu"
    if precision != "fp32" and (naive or not on_cpu or not native_kernel.serves(checkpoint.config)):
        # bf16 lives in the native step; the naive recompute, a GPU and the models the step does not serve
        # (image models such as Breakout, full-attention models) keep their own exact path.
        if not naive:
            log.warning(
                "precision does not apply to this model: fp32",
                extra={"model": checkpoint.name, "precision": precision, "device": device},
            )
        precision = "fp32"
    engine = PolicyEngine(
        checkpoint,
        incremental=False if naive else None,
        device=device,
        n_slots=16 if on_cpu else n_slots,
        precision=precision,
    )
    if not on_cpu:
        engine.warm_up()
    return engine


def canary_draw(version: str, sid: str) -> float:
    """Where session `sid` falls in [0, 1) for the canary `version`: a hash of both, so every replica and every
    retry of a create with the same id decide alike, and each new canary draws its sessions afresh."""
    digest = hashlib.sha256(f"{version}\0{sid}".encode()).digest()
    return int.from_bytes(digest[:8], "big") / 2**64


@dataclass
class LoadedModel:
    """One version of a model, ready to serve.

    Attributes:
        name: Model name clients use (for the first version, the checkpoint directory's name).
        path: Checkpoint directory.
        checkpoint: The loaded checkpoint.
        engine: The engine answering its acts (incremental for `window` models, recompute otherwise).
        state: `serving` (new sessions may use it) or `draining` (only its sessions).
    """

    name: str
    path: Path
    checkpoint: Checkpoint
    engine: PolicyEngine
    state: str = SERVING

    @property
    def version(self) -> str:
        """The served version."""
        return self.checkpoint.version or MEMORY_VERSION

    @property
    def fingerprint(self) -> str:
        """The checkpoint's fingerprint (empty when built in memory)."""
        return self.checkpoint.fingerprint

    @property
    def key(self) -> str:
        """`name@version`."""
        return model_key(self.name, self.version)


@dataclass
class ModelVersions:
    """Every loaded version of one model name.

    Attributes:
        default: The version new sessions get.
        canary: (version, share): that version gets this share of the new sessions that name no version.
    """

    name: str
    versions: dict[str, LoadedModel] = field(default_factory=dict)
    default: str = ""
    canary: tuple[str, float] | None = None

    def for_new_session(self, sid: str) -> LoadedModel:
        """The version a new session `sid` that names none gets: the canary for its share of ids, else the
        default."""
        if self.canary is not None:
            version, share = self.canary
            if canary_draw(version, sid) < share:
                return self.versions[version]
        return self.versions[self.default]


@dataclass
class ModelRegistry:
    """Loaded models by name and version, plus the errors of checkpoints that failed to load at startup."""

    names: dict[str, ModelVersions] = field(default_factory=dict)
    errors: dict[str, str] = field(default_factory=dict)

    @property
    def models(self) -> dict[str, LoadedModel]:
        """The default version of each model, by name."""
        return {n: mv.versions[mv.default] for n, mv in self.names.items()}

    def loaded(self) -> list[LoadedModel]:
        """Every loaded version of every model."""
        return [m for mv in self.names.values() for m in mv.versions.values()]

    @classmethod
    def load(
        cls,
        paths: list[Path],
        naive: bool = False,
        device: str = "cpu",
        n_slots: int = 16,
        precision: str = "fp32",
    ) -> ModelRegistry:
        """Load every checkpoint found under `paths`, each the one version of the model named by its directory; a
        broken one is logged and skipped.

        `naive` serves every model by the reference recompute (the exactness oracle and benchmark baseline);
        `device`, `n_slots` and `precision` as in `engine_for`.
        """
        reg = cls()
        for d in discover(paths):
            name = d.name
            if name in reg.names:
                reg.errors[str(d)] = (
                    f"duplicate model name {name!r} (already loaded from {reg.models[name].path})"
                )
                log.error("checkpoint skipped", extra={"path": str(d), "error": reg.errors[str(d)]})
                continue
            try:
                m = load_model(name, d, naive, device=device, n_slots=n_slots, precision=precision)
            except CheckpointError as e:
                reg.errors[str(d)] = str(e)
                log.error("checkpoint failed to load", extra={"path": str(d), "error": str(e)})
                continue
            reg.add(m)
        return reg

    @classmethod
    def of(cls, *checkpoints: Checkpoint, naive: bool = False) -> ModelRegistry:
        """A registry of already-loaded checkpoints (tests, notebooks)."""
        reg = cls()
        for c in checkpoints:
            reg.add(LoadedModel(c.name, Path("."), c, engine_for(c, naive)))
        return reg

    # ----- the table ------------------------------------------------------------------------------------------
    def add(self, m: LoadedModel) -> LoadedModel:
        """Add a loaded version (the default when it is its model's first); answers the version already loaded
        when it is the same checkpoint (a repeated load).

        Raises:
            AlreadyExists: this version is loaded from a checkpoint with another fingerprint.
            InvalidArgument: its environment or spaces differ from the default version's.
        """
        mv = self.names.get(m.name)
        if mv is None:
            self.names[m.name] = ModelVersions(m.name, {m.version: m}, m.version)
            return m
        have = mv.versions.get(m.version)
        if have is not None:
            if have.fingerprint != m.fingerprint:
                raise AlreadyExists(
                    f"version {m.version!r} of model {m.name!r} is already loaded with fingerprint "
                    f"{have.fingerprint[:16]}..., and {m.path} has fingerprint {m.fingerprint[:16]}...: give the "
                    "new checkpoint another version in its gmt.json"
                )
            return have
        base, new = mv.versions[mv.default].checkpoint, m.checkpoint
        for what in ("env_id", "observation_space", "action_space"):
            if getattr(base, what) != getattr(new, what):
                raise InvalidArgument(
                    f"{m.path} cannot be a version of model {m.name!r}: its {what} differs from version "
                    f"{mv.default!r}'s ({getattr(new, what)!r} vs {getattr(base, what)!r})"
                )
        mv.versions[m.version] = m
        return m

    def entry(self, name: str) -> ModelVersions:
        """The versions of model `name`.

        Raises:
            NotFound: no such model.
        """
        try:
            return self.names[name]
        except KeyError:
            raise NotFound(f"unknown model {name!r}; loaded models: {self._names()}") from None

    def version(self, name: str, version: str) -> LoadedModel:
        """Version `version` of model `name`.

        Raises:
            NotFound: no such model or version.
        """
        mv = self.entry(name)
        try:
            return mv.versions[version]
        except KeyError:
            raise NotFound(
                f"model {name!r} has no version {version!r}; loaded versions: {', '.join(mv.versions)}"
            ) from None

    def find(self, name: str, version: str) -> LoadedModel | None:
        """Version `version` of model `name` ('' = the default version), or None where not loaded."""
        mv = self.names.get(name)
        if mv is None:
            return None
        return mv.versions.get(version or mv.default)

    def get(self, name: str) -> LoadedModel:
        """The default version of model `name`.

        Raises:
            NotFound: no such model.
        """
        mv = self.entry(name)
        return mv.versions[mv.default]

    def resolve(self, name: str | None) -> ModelVersions:
        """The versions of model `name`, or of the only loaded model when `name` is empty.

        Raises:
            InvalidArgument: no name given while several models are loaded.
            NotFound: no such model.
            Unavailable: no model is loaded at all.
        """
        if not self.names:
            raise Unavailable("no model is loaded on this server")
        if name:
            return self.entry(name)
        if len(self.names) == 1:
            return next(iter(self.names.values()))
        raise InvalidArgument(f"model is required: loaded models are {self._names()}")

    def for_new_session(self, name: str | None, version: str | None, sid: str) -> LoadedModel:
        """The version a new session gets: the one it names (which must be serving), else the canary or default.

        Raises:
            FailedPrecondition: the named version is draining.
            InvalidArgument / NotFound / Unavailable: as `resolve` and `version`.
        """
        mv = self.resolve(name)
        if not version:
            return mv.for_new_session(sid)
        m = self.version(mv.name, version)
        if m.state != SERVING:
            raise FailedPrecondition(
                f"version {version!r} of model {mv.name!r} is draining: it takes no new sessions; name a serving "
                f"version or none (default {mv.default!r})"
            )
        return m

    def promote(self, name: str, version: str, share: float) -> None:
        """Make `version` the default (share 1), or the canary that gets `share` of new sessions (0 < share < 1).
        A draining version serves again.

        Raises:
            InvalidArgument: share outside (0, 1], or a canary share for the default version.
            NotFound: no such model or version.
        """
        mv, m = self.entry(name), self.version(name, version)
        if isinstance(share, bool) or not isinstance(share, int | float) or not 0 < share <= 1:
            raise InvalidArgument(f"share must be a number in (0, 1], got {share!r}")
        if share < 1 and version == mv.default:
            raise InvalidArgument(
                f"version {version!r} is the default of model {name!r}: a canary is another version"
            )
        m.state = SERVING
        if share >= 1:
            mv.default, mv.canary = version, None
        else:
            mv.canary = (version, float(share))

    def drain(self, name: str, version: str) -> LoadedModel:
        """Stop giving `version` new sessions (a canary is stopped).

        Raises:
            FailedPrecondition: it is the default version (promote another first).
            NotFound: no such model or version.
        """
        mv, m = self.entry(name), self.version(name, version)
        if version == mv.default:
            raise FailedPrecondition(
                f"version {version!r} is the default of model {name!r}: promote another version before draining it"
            )
        m.state = DRAINING
        if mv.canary is not None and mv.canary[0] == version:
            mv.canary = None
        return m

    def remove(self, name: str, version: str) -> LoadedModel:
        """Take `version` out of the table (the model goes with its last version).

        Raises:
            FailedPrecondition: it is the default while other versions are loaded, or the only version this server
                serves (a server left with none answers nothing).
            NotFound: no such model or version.
        """
        mv, m = self.entry(name), self.version(name, version)
        if len(self.loaded()) == 1:
            raise FailedPrecondition(
                f"version {version!r} of model {name!r} is the only version this server serves: load another "
                "before unloading it"
            )
        if version == mv.default and len(mv.versions) > 1:
            raise FailedPrecondition(
                f"version {version!r} is the default of model {name!r}: promote another version before unloading it"
            )
        del mv.versions[version]
        if mv.canary is not None and mv.canary[0] == version:
            mv.canary = None
        if not mv.versions:
            del self.names[name]
        return m

    def _names(self) -> str:
        return ", ".join(sorted(self.names)) or "(none)"


def load_model(
    name: str,
    path: Path,
    naive: bool = False,
    expect_fingerprint: str | None = None,
    state: str = SERVING,
    device: str = "cpu",
    n_slots: int = 16,
    precision: str = "fp32",
) -> LoadedModel:
    """Load the checkpoint at `path` as a version of model `name`, with its engine (slow: run it in a thread).

    Raises:
        CheckpointError: the checkpoint is missing, malformed or refused (see `load_checkpoint`), or its engine
            cannot serve it.
    """
    try:
        ckpt = load_checkpoint(path, name=name, expect_fingerprint=expect_fingerprint)
        engine = engine_for(ckpt, naive, device, n_slots, precision)
    except CheckpointError:
        raise
    except Exception as e:  # noqa: BLE001 - whatever a malformed checkpoint makes torch or the engine raise
        raise CheckpointError(f"{path} cannot be served: {type(e).__name__}: {e}") from e
    m = LoadedModel(name, path, ckpt, engine, state)
    info = engine.describe()
    log.info(
        "model loaded",
        extra={
            "model": name,
            "version": m.version,
            "path": str(path),
            "env_id": ckpt.env_id,
            "goals": len(ckpt.goals),
            "attention": ckpt.config.attention,
            "engine": info.path,
            "kernel": info.kernel,
            "precision": info.precision,
            "device": engine.device,
        },
    )
    return m


def candidates(roots: list[Path], depth: int = SCAN_DEPTH) -> list[Path]:
    """Checkpoint directories at most `depth` levels under each root (the root itself included)."""
    found: list[Path] = []
    level = [r for r in roots if r.is_dir()]
    for _ in range(depth + 1):
        found.extend(d for d in level if (d / META).is_file())
        level = sorted(c for d in level if not (d / META).is_file() for c in d.iterdir() if c.is_dir())
    return found


def find_by_fingerprint(roots: list[Path], version: str, fp: str) -> Path | None:
    """The checkpoint directory under `roots` whose fingerprint is `fp` (or, when `fp` is empty, whose version is
    `version`); reading each candidate's weights is the price of finding it. Slow: run it in a thread."""
    for d in candidates(roots):
        try:
            meta = read_meta(d)
            named = meta.get("version")
            if named is not None and named != version:
                continue  # it names another version: not this one, whatever its weights
            got = fingerprint((d / WEIGHTS).read_bytes(), meta)
            if (got == fp) if fp else (version_of(meta, got) == version):
                return d
        except (CheckpointError, OSError):
            continue
    return None
