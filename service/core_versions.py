"""The core's control plane: the versions of each model, loaded, promoted, drained, unloaded and adopted, their
batchers, and the default and canary kept across restarts (`gmt.service.model_state`).
"""

from __future__ import annotations

import asyncio
import logging
import re
from dataclasses import fields
from pathlib import Path

from gmt.model.checkpoint import CheckpointError, model_info
from gmt.service.batcher import REMOTE_STORE_PARTS, MicroBatcher
from gmt.service.core_state import CoreState
from gmt.service.errors import FailedPrecondition, InvalidArgument, PermissionDenied, ServiceError
from gmt.service.ids import DOT_SEGMENTS, MAX_PATH_LENGTH, check_version
from gmt.service.model_state import entry_of, model_state_for, restore
from gmt.service.registry import (
    DRAINING,
    LoadedModel,
    ModelVersions,
    find_by_fingerprint,
    load_model,
    model_key,
)
from gmt.service.sessions import Session
from gmt.service.views import ModelView, VersionView

log = logging.getLogger("gmt.core")

UNLOAD_WAIT_S = 5.0  # longest wait, in a forced unload, for the acts already in the version's batcher
_HEX = re.compile(r"[0-9a-fA-F]{12,64}")
_MODEL_NAME = re.compile(r"[A-Za-z0-9._-]{1,128}")


class Versions(CoreState):
    """Model versions, a part of `gmt.service.core.Core` (it owns `_batchers`, `_admin`, `_adopting`, `_unloaded`,
    `_tasks` and `model_state`; `CoreState` makes them)."""

    async def _restore_model_state(self) -> None:
        """Serve the defaults and canaries saved before a restart (`gmt.service.model_state`)."""
        self.model_state = model_state_for(list(self.settings.checkpoints), self.store)
        try:
            saved = await self.model_state.read()
        except (OSError, ValueError, ServiceError) as e:
            log.error(
                "saved model state unreadable", extra={"where": self.model_state.where, "error": str(e)}
            )
            return
        roots = list(self.settings.checkpoints)
        await restore(
            self.registry, saved, roots, self.settings.naive, self.checkpoint_path, self._engine_placement()
        )

    async def _save_model_state(self, name: str) -> None:
        """Keep model `name`'s default and canary for the next start (a failure is logged: the change stands)."""
        mv = self.registry.names.get(name)
        try:
            await self.model_state.write(name, entry_of(mv) if mv is not None else None)
        except (OSError, ServiceError) as e:
            log.error(
                "model state not saved: a restart serves the previous default",
                extra={"model": name, "where": self.model_state.where, "error": str(e)},
            )

    def _view_model(self, mv: ModelVersions) -> ModelView:
        m = mv.versions[mv.default]
        c = m.checkpoint
        info = model_info(
            c,
            name=m.name,
            action_modes=m.engine.describe().action_modes,
            switch_relabel_steps=m.engine.switch_relabel_steps,
        )
        return ModelView(
            **{f.name: getattr(info, f.name) for f in fields(info)},
            discrete_actions=c.config.discrete_actions,
            version=m.version,
            versions=tuple(
                VersionView(v.version, self.store.local_count(v.key), v.state, v.fingerprint)
                for v in mv.versions.values()
            ),
            default_version=mv.default,
            canary=mv.canary,
        )

    def list_models(self) -> list[ModelView]:
        """Every loaded model, by name."""
        return [self._view_model(self.registry.names[n]) for n in sorted(self.registry.names)]

    def get_model(self, name: str) -> ModelView:
        """One model. Raises NotFound."""
        return self._view_model(self.registry.entry(name))

    def _engine_placement(self) -> dict:
        """Where and how a loaded version's engine runs: `--device`, its pool sized for `--max-sessions` off the
        CPU, and `--precision`."""
        s = self.settings
        return {"device": s.device, "n_slots": s.max_sessions, "precision": s.precision}

    def _start_batcher(self, m: LoadedModel) -> None:
        """Start the micro-batcher of a version newly in the registry."""
        s = self.settings
        b = MicroBatcher(
            m.engine,
            self._executor,
            max_batch=1 if s.naive else s.max_batch,
            max_wait_s=0.0 if s.naive else s.batch_wait_ms / 1000.0,
            observe=lambda size, sec, n=m.name, v=m.version: self.metrics.observe_batch(n, v, size, sec),
            inline_alone=m.engine.describe().kernel == "native",
            call_threads=s.call_threads,
            parts=REMOTE_STORE_PARTS if self.store.remote else 2,
        )
        b.start()
        self.metrics.track_queue(m.name, m.version, lambda b=b: b.queued)
        self._batchers[m.key] = b
        self._count_models()

    def _count_models(self) -> None:
        self.metrics.models_loaded.set(len(self.registry.names))
        self.metrics.versions_loaded.set(len(self._batchers))

    def _batcher(self, m: LoadedModel) -> MicroBatcher:
        b = self._batchers.get(m.key)
        if b is None or b.engine.pool is not m.engine.pool:  # gone, or loaded again since `m` was looked up
            raise FailedPrecondition(
                f"version {m.version!r} of model {m.name!r} was unloaded from this server"
            )
        return b

    async def _stop(self, m: LoadedModel, wait_s: float = 0.0) -> None:
        """Stop serving a version taken out of the registry: its batcher ends (after the acts it holds, for up to
        `wait_s`), and with the last reference the engine, its weights and its session pool are freed."""
        b = self._batchers.pop(m.key, None)
        self.metrics.untrack_queue(m.name, m.version)
        self._count_models()
        if b is not None:
            await b.close(wait_s)
        log.info("model version unloaded", extra={"model": m.name, "version": m.version})

    def _unload_if_drained(self, m: LoadedModel) -> None:
        """Unload a draining version once this server holds none of its sessions."""
        if m.state != DRAINING or self.store.local_count(m.key) or self.closing:
            return
        if self.registry.find(m.name, m.version) is not m:
            return  # already out
        self.registry.remove(m.name, m.version)
        task = asyncio.get_running_loop().create_task(self._stop(m), name=f"unload {m.key}")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    def checkpoint_path(self, path: object) -> Path:
        """The checkpoint directory `path` names, if it is under a checkpoint root (`settings.checkpoints`).

        A relative path is taken from the server's working directory, else from each root.

        Raises:
            InvalidArgument: not a non-empty string, or nothing by that name under the roots or elsewhere.
            PermissionDenied: it is not under a checkpoint root (symbolic links resolved).
        """
        if not isinstance(path, str) or not path or "\0" in path:
            raise InvalidArgument("path must name a checkpoint directory under the checkpoint roots")
        if len(path) > MAX_PATH_LENGTH:
            raise InvalidArgument(
                f"path is {len(path)} characters long: a checkpoint path has at most {MAX_PATH_LENGTH}"
            )
        roots = [r.resolve() for r in self.settings.checkpoints]
        p = Path(path)
        tries = [p] if p.is_absolute() else [Path.cwd() / p, *(r / p for r in roots)]
        shown = ", ".join(str(r) for r in self.settings.checkpoints)
        try:
            found = [t.resolve() for t in tries]
            inside = [t for t in found if any(t == r or t.is_relative_to(r) for r in roots)]
            for t in inside:
                if t.exists():
                    return t
            if inside and not any(t.exists() for t in found):
                raise InvalidArgument(f"no checkpoint {path!r} under the checkpoint roots ({shown})")
        except OSError as e:  # a name longer than the file system allows, a loop of links, ...
            raise InvalidArgument(f"path {path!r} cannot name a checkpoint directory: {e.strerror}") from None
        raise PermissionDenied(
            f"{path!r} is not under the checkpoint roots ({shown}): this server loads checkpoints from there only"
        )

    async def load_version(self, name: str, path: str, fingerprint: str | None = None) -> VersionView:
        """Load the checkpoint at `path` as a version of model `name` (a new name starts a new model); the load
        runs in a thread, so acts keep being answered. Loading the version again is answered the loaded one.

        Args:
            fingerprint: Refuse the checkpoint unless its fingerprint starts with this (12 to 64 hex digits).

        Raises:
            InvalidArgument: a bad name or fingerprint, a checkpoint that cannot be loaded (the message names the
                problem), or spaces that differ from the model's default version.
            PermissionDenied: `path` is not under a checkpoint root.
            AlreadyExists: the version is loaded from another checkpoint (another fingerprint).
        """
        self._check_serving()
        if not isinstance(name, str) or not (
            name in self.registry.names or (_MODEL_NAME.fullmatch(name) and name not in DOT_SEGMENTS)
        ):
            raise InvalidArgument(
                "a new model's name must be 1 to 128 letters, digits, '.', '_' or '-', and not '.' or '..' "
                "(HTTP clients rewrite those in a path)"
            )
        if fingerprint is not None and not (isinstance(fingerprint, str) and _HEX.fullmatch(fingerprint)):
            raise InvalidArgument(
                "fingerprint must be 12 to 64 hex digits (a prefix of the checkpoint's sha256)"
            )
        d = self.checkpoint_path(path)
        async with self._admin:
            try:
                m = await asyncio.to_thread(
                    load_model, name, d, self.settings.naive, fingerprint, **self._engine_placement()
                )
            except CheckpointError as e:
                raise InvalidArgument(f"checkpoint refused: {e}") from None
            except OSError as e:  # unreadable files (permissions, a directory where a file should be, ...)
                raise InvalidArgument(
                    f"checkpoint refused: cannot read {e.filename or d}: {e.strerror}"
                ) from None
            have = self.registry.add(m)
            self._unloaded.discard(m.key)
            if have is m:
                self._start_batcher(m)
                log.info("model version added", extra={"model": name, "version": m.version, "path": str(d)})
                if self.registry.names[name].default == m.version:
                    await self._save_model_state(name)  # a new model: its first version is its default
        return self._view_version(have)

    def _view_version(self, m: LoadedModel) -> VersionView:
        return VersionView(m.version, self.store.local_count(m.key), m.state, m.fingerprint)

    async def promote(self, name: str, version: str, share: float = 1.0) -> ModelView:
        """Make `version` the default of model `name` (share 1), or a canary that gets `share` of the new sessions
        that name no version.

        Raises:
            InvalidArgument: share not in (0, 1], or a canary share for the default version.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            self.registry.promote(name, check_version(version), share)
            await self._save_model_state(name)
        log.info("model version promoted", extra={"model": name, "version": version, "share": share})
        return self.get_model(name)

    async def drain(self, name: str, version: str) -> ModelView:
        """Give `version` no new sessions; it is unloaded once this server holds none of its sessions.

        Raises:
            FailedPrecondition: it is the default version.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            m = self.registry.drain(name, check_version(version))
            log.info("model version draining", extra={"model": name, "version": version})
            await self._save_model_state(name)  # a drained canary is no longer one
            self._unload_if_drained(m)
        return self.get_model(name) if name in self.registry.names else self._gone(name)

    async def unload(self, name: str, version: str, force: bool = False) -> ModelView:
        """Unload `version` now. With `force`, also while sessions use it: their next calls here answer
        failed_precondition (until the version is loaded again).

        Raises:
            FailedPrecondition: sessions use it (and not `force`), or it is the default while other versions are
                loaded.
            NotFound: no such model or version on this server.
        """
        self._check_serving()
        async with self._admin:
            m = self.registry.version(name, check_version(version))
            n = self.store.local_count(m.key)
            if n and not force:
                raise FailedPrecondition(
                    f"{n} session(s) on this server use version {version!r} of model {name!r}: drain it (it is "
                    "unloaded when they end), or unload with force=true (their next calls fail)"
                )
            self.registry.remove(name, version)
            await self._save_model_state(name)
            if n:
                self._unloaded.add(m.key)
            await self._stop(m, wait_s=UNLOAD_WAIT_S)
        return self.get_model(name) if name in self.registry.names else self._gone(name)

    @staticmethod
    def _gone(name: str) -> ModelView:
        """The view of a model whose last version was unloaded: no versions."""
        return ModelView(name, "", {}, {}, 0, "", discrete_actions=False)

    async def _model_of(self, s: Session) -> LoadedModel:
        """The loaded version a session runs; a version this server lacks is found under the checkpoint roots by
        its fingerprint and loaded (in a thread).

        Raises:
            FailedPrecondition: this server does not serve the model, or the version was unloaded here with
                force, or it cannot be found or loaded.
        """
        if s.model not in self.registry.names:
            raise FailedPrecondition(
                f"session {s.id!r} runs model {s.model!r}, which this server does not serve"
            )
        m = self.registry.find(s.model, s.model_version)
        if m is not None:
            if s.fingerprint and m.fingerprint and m.fingerprint != s.fingerprint:
                raise FailedPrecondition(
                    f"session {s.id!r} runs version {s.model_version!r} of model {s.model!r} with fingerprint "
                    f"{s.fingerprint[:16]}..., but this server's version {m.version!r} has fingerprint "
                    f"{m.fingerprint[:16]}..."
                )
            return m
        key = model_key(s.model, s.model_version)
        if key in self._unloaded:
            raise FailedPrecondition(
                f"session {s.id!r} runs version {s.model_version!r} of model {s.model!r}, which was unloaded from "
                "this server (forced); create a new session"
            )
        fut = self._adopting.get(key)
        if fut is None:
            fut = self._adopting[key] = asyncio.ensure_future(
                self._adopt(s.model, s.model_version, s.fingerprint)
            )
            fut.add_done_callback(lambda _: self._adopting.pop(key, None))
        return await asyncio.shield(fut)

    async def _adopt(self, name: str, version: str, fp: str) -> LoadedModel:
        """Find version `version` (fingerprint `fp`) of model `name` under the checkpoint roots and load it, as a
        draining version: it serves the sessions that need it and is unloaded when none is left here."""
        roots = list(self.settings.checkpoints)
        where = ", ".join(str(r) for r in roots)
        path = await asyncio.to_thread(find_by_fingerprint, roots, version, fp)
        if path is None:
            raise FailedPrecondition(
                f"version {version!r} of model {name!r} is not loaded on this server, and no checkpoint with its "
                f"fingerprint ({fp[:16] or 'unknown'}...) is under the checkpoint roots ({where})"
            )
        async with self._admin:
            m = self.registry.find(name, version)
            if m is not None:
                return m
            try:
                m = await asyncio.to_thread(
                    load_model,
                    name,
                    path,
                    self.settings.naive,
                    fp or None,
                    DRAINING,
                    **self._engine_placement(),
                )
                self.registry.add(m)
            except (CheckpointError, ServiceError) as e:
                msg = e.message if isinstance(e, ServiceError) else str(e)
                raise FailedPrecondition(
                    f"version {version!r} of model {name!r} is not loaded on this server and could not be loaded "
                    f"from {path}: {msg}"
                ) from None
            self._start_batcher(m)
            log.info("model version adopted", extra={"model": name, "version": version, "path": str(path)})
            return m

    def _dropped(self, sid: str, key: str) -> None:
        """Free what this process holds for a session that is gone (closed, expired or swept), and unload its
        version when it was the last session of a draining one."""
        name, _, version = key.rpartition("@")
        m = self.registry.find(name, version) if self.registry else None
        if m is not None:
            m.engine.forget(sid)
            self._unload_if_drained(m)
