"""Each model's default version and canary, kept across restarts (docs/models.md, "After a restart").

The core writes a model's entry after every management call that changes it (load, promote, drain, unload) and
reads them all at start, after the checkpoints found under the roots are loaded: a saved default or canary that is
not loaded yet is loaded from its saved path (or found under the roots by its fingerprint) and promoted again.

One server keeps them in a JSON file beside its checkpoints (`gmt-models.json` in the first root that is a folder
of checkpoints, written atomically; none when every root is a checkpoint directory itself); replicas sharing a Redis store keep them in the store (`RedisSessionStore.model_states`), so a
restarted replica serves what the cluster promoted.
"""

from __future__ import annotations

import abc
import asyncio
import json
import logging
import os
import tempfile
from collections.abc import Callable
from pathlib import Path

from gmt.model.checkpoint import META, CheckpointError
from gmt.service.errors import ServiceError
from gmt.service.registry import LoadedModel, ModelRegistry, ModelVersions, find_by_fingerprint, load_model

log = logging.getLogger("gmt.model_state")
STATE_FILE = "gmt-models.json"  # the state file's name beside the checkpoint roots


def entry_of(mv: ModelVersions) -> dict:
    """A model's saved entry: its default version and its canary (version, share), each with fingerprint and path."""

    def ref(m: LoadedModel) -> dict:
        return {"version": m.version, "fingerprint": m.fingerprint, "path": str(m.path.resolve())}

    canary = None
    if mv.canary is not None:
        version, share = mv.canary
        canary = {**ref(mv.versions[version]), "share": share}
    return {"default": ref(mv.versions[mv.default]), "canary": canary}


class ModelState(abc.ABC):
    """Where the model entries are kept."""

    where: str  # for the start-up log and `GET /models`: "file <path>", "redis" or "off"

    @abc.abstractmethod
    async def read(self) -> dict[str, dict]:
        """Every saved entry, by model name (empty when none is saved)."""

    @abc.abstractmethod
    async def write(self, name: str, entry: dict | None) -> None:
        """Save model `name`'s entry (None: forget the model)."""


class NoModelState(ModelState):
    """Nothing is kept: a registry built in memory, or checkpoint roots that are all checkpoint directories
    themselves (such a server loads versions only from inside them)."""

    where = "off"

    async def read(self) -> dict[str, dict]:
        return {}

    async def write(self, name: str, entry: dict | None) -> None:
        return None


class FileModelState(ModelState):
    """A JSON file, `{"models": {name: entry}}`, replaced atomically (a temporary file renamed over it)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.where = f"file {path}"

    def _read(self) -> dict[str, dict]:
        try:
            data = json.loads(self.path.read_text())
        except FileNotFoundError:
            return {}
        models = data.get("models") if isinstance(data, dict) else None
        if not isinstance(models, dict):
            raise ValueError(f"{self.path} has no 'models' object")
        return models

    async def read(self) -> dict[str, dict]:
        return await asyncio.to_thread(self._read)

    def _write(self, name: str, entry: dict | None) -> None:
        try:
            models = self._read()
        except (OSError, ValueError):
            models = {}  # an unreadable file is replaced (its problem was logged at start)
        if entry is None:
            if models.pop(name, None) is None:
                return  # nothing saved for it: no file to write
        else:
            models[name] = entry
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                json.dump({"models": models}, f, indent=2, sort_keys=True)
                f.write("\n")
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise

    async def write(self, name: str, entry: dict | None) -> None:
        await asyncio.to_thread(self._write, name, entry)


class StoreModelState(ModelState):
    """The shared Redis store's `models` hash (one field per model)."""

    where = "redis"

    def __init__(self, store) -> None:
        self.store = store

    async def read(self) -> dict[str, dict]:
        return await self.store.model_states()

    async def write(self, name: str, entry: dict | None) -> None:
        await self.store.save_model_state(name, entry)


def state_file(roots: list[Path]) -> Path | None:
    """The state file of a server with checkpoint roots `roots`: in the first root that is a folder of checkpoints
    (not itself a checkpoint directory, which is never written to); None when there is none."""
    for root in roots:
        if root.is_dir() and not (root / META).is_file():
            return root / STATE_FILE
    return None


def model_state_for(roots: list[Path], store) -> ModelState:
    """The shared store's model state when it keeps one (Redis), else the file beside `roots`."""
    if hasattr(store, "model_states"):
        return StoreModelState(store)
    path = state_file(roots)
    return FileModelState(path) if path is not None else NoModelState()


async def restore(
    registry: ModelRegistry,
    saved: dict[str, dict],
    roots: list[Path],
    naive: bool,
    under_roots: Callable[[str], Path],
    placement: dict | None = None,
) -> list[LoadedModel]:
    """Make each saved default and canary current again, loading those not loaded yet; answers the versions it
    loaded. An entry that cannot be restored (its checkpoint gone or refused) is logged and the model keeps the
    version found at start.

    Args:
        under_roots: Checks that a saved path is under the checkpoint roots (`Core.checkpoint_path`).
        placement: `load_model`'s device, n_slots and precision (`Versions._engine_placement`): a restored
            version runs as the versions loaded at start do.
    """
    added: list[LoadedModel] = []
    for name, entry in saved.items():
        try:
            refs = [(entry["default"], 1.0)]
            if entry.get("canary"):
                refs.append((entry["canary"], float(entry["canary"]["share"])))
            for ref, share in refs:
                version, fp = str(ref["version"]), str(ref.get("fingerprint") or "")
                m = registry.find(name, version)
                if m is None:
                    m = await asyncio.to_thread(
                        _load,
                        name,
                        version,
                        fp,
                        str(ref.get("path", "")),
                        roots,
                        naive,
                        under_roots,
                        placement or {},
                    )
                    registry.add(m)
                    added.append(m)
                registry.promote(name, version, share)
            log.info(
                "model state restored",
                extra={"model": name, "default": entry["default"]["version"], "canary": entry.get("canary")},
            )
        except (KeyError, TypeError, ValueError, CheckpointError, ServiceError) as e:
            msg = e.message if isinstance(e, ServiceError) else f"{type(e).__name__}: {e}"
            log.error("saved model state not restored", extra={"model": name, "error": msg})
    return added


def _load(
    name: str,
    version: str,
    fp: str,
    path: str,
    roots: list[Path],
    naive: bool,
    under_roots: Callable[[str], Path],
    placement: dict,
) -> LoadedModel:
    """Load a saved version (with `placement`, as `restore`'s): from its saved path when that still holds it, else
    found under the roots by fingerprint."""
    d: Path | None = None
    if path and Path(path).is_dir():
        d = under_roots(path)
    if d is None:
        d = find_by_fingerprint(roots, version, fp)
    if d is None:
        raise CheckpointError(
            f"no checkpoint of version {version!r} (fingerprint {fp[:16]}...) under the roots"
        )
    return load_model(name, d, naive, fp or None, **placement)
