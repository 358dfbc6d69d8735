"""Server settings: environment variables prefixed `GMT_`, overridden by `gmt serve` flags.

What a user sets is a flag of `gmt serve` as well; the tuning knobs (`TUNING`: batching, event loop, connection
limits and timeouts, the reference path) are set in the environment only, so that `gmt serve --help` lists what a
deployment chooses. docs/serving.md has one table of them all.
"""

from __future__ import annotations

import os
import re
import socket
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, PrivateAttr, SecretStr, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from gmt.service.records import MAX_RECORD_STEPS

_REPLICA_ID = re.compile(r"[\x21-\x7e]{1,128}")  # valid in an HTTP header and in gRPC metadata


class Settings(BaseSettings):
    """Everything `gmt serve` can be told; each field is also `GMT_<FIELD>` in the environment.

    Attributes:
        checkpoints: Checkpoint directories, or folders whose sub-directories are checkpoints (repeat the flag;
            comma-separated in GMT_CHECKPOINTS).
        host: Interface both servers bind.
        rest_port: REST port (0 = any free port).
        grpc_port: gRPC port (0 = any free port).
        max_sessions: Live sessions allowed at once (all models, all replicas sharing a Redis store).
        idle_timeout_s: A session unused for this long expires.
        batch_wait_ms: Longest time a request waits for others to join its batch.
        max_batch: Most requests in one forward pass.
        inference_threads: Worker threads running forward passes (and torch intra-op threads).
        call_threads: Threads the native step of one many-session call's pass (`POST /act`, `ActBatch`; from 64
            rows) splits its rows between, the same answers. Such a pass runs while the event loop mostly waits
            for it; single acts' passes keep one thread, as the loop is busy beside them (1 = never split).
        max_request_bytes: Largest REST body / gRPC message accepted.
        auth_token: Bearer token required on every call except health checks (None = no auth); with
            auth_tokens, one more key, named `default`.
        auth_tokens: A file of named keys, one `name:token` a line (`gmt.service.keys`): each is a bearer token
            of its own, and a session is seen only by the key that created it (and the admin token).
        admin_token: Bearer token of the model management calls (load, promote, drain, unload a version); None:
            the auth token, and with no token at all only a client on this machine, not through a proxy
            (`gmt.service.admin`).
        redis_url: Keep sessions in this Redis instead of in memory: one server (redis://localhost:6379/0) or the
            primary that Redis Sentinel watches (redis+sentinel://h1:26379,h2:26379,h3:26379/<service-name>, a
            database number may follow: /<service-name>/1).
        store_min_replicas: With a Redis store, acknowledge a step (and a new session) only once this many Redis
            replicas hold it (Redis WAIT); fewer within the wait timeout answers `unavailable` (0 = do not wait).
        store_wait_timeout_s: Longest wait for those replicas (under the store's 5 s socket timeout).
        store_spin_us: With a Redis store, a lone session's write (the only session this replica serves, no other
            write in flight) waits for Redis's reply by polling the socket for up to this long instead of sleeping
            in the event loop (0 = never poll, the default: on the shared 2-core machine polling 500 us made the
            lone session's p50 no shorter, docs/performance.md; across a network it only burns CPU).
        log_format: `json` or `kv` (key=value) log lines.
        log_level: Python logging level name.
        shutdown_grace_s: Time in-flight calls get to finish on SIGTERM / SIGINT.
        keep_alive_s: An idle HTTP keep-alive connection is closed after this long. Longer than a proxy's
            upstream keep-alive (60 s in cluster/nginx.conf), so that the proxy never reuses a connection the
            server is just closing (which it answers with a 502).
        header_timeout_s: A REST request's headers must arrive within this long of its first byte (of the
            connection, for its first request), else 408 and the connection is closed (nginx:
            client_header_timeout).
        body_timeout_s: A REST request's body must arrive within this long of its headers, else the connection is
            closed (nginx: client_body_timeout, which times each read instead).
        body_min_rate: Bytes per second a REST request's body must average after its first second, else 408 and
            the connection is closed (0: no minimum; Apache's mod_reqtimeout MinRate).
        rest_max_connections: Open REST connections at most (0 = half the descriptor limit above a reserve, see
            docs/reliability.md); a new one past it closes the oldest connection without a request in progress.
        rest_max_connections_per_peer: REST connections one client address may hold while the server is full (0 =
            half of rest_max_connections): past it, its new connections are refused and its slow ones go first.
        grpc_max_connections: Open gRPC connections at most (0 = from the descriptor limit); gRPC closes new ones
            past it at once.
        grpc_handshake_timeout_s: A gRPC connection must complete its HTTP/2 handshake within this long.
        grpc_window_bytes: HTTP/2 flow-control window of each gRPC stream: the most a stream's client may send
            that the server has not read yet (a larger message still arrives: the window opens for it).
        grpc_max_streams_per_connection: Concurrent gRPC streams on one connection (HTTP/2
            SETTINGS_MAX_CONCURRENT_STREAMS).
        grpc_max_concurrent_rpcs: Concurrent gRPC calls (Control streams included) of the whole server; one past
            it answers RESOURCE_EXHAUSTED at once.
        grpc_write_timeout_s: A Control stream whose client takes no answer for this long (its flow-control window
            stays closed) ends with RESOURCE_EXHAUSTED, which the client reads after the answers still queued.
        event_loop: `uvloop` (the default: a faster loop for both transports) or `asyncio`.
        device: Where the networks run: `cpu` (the native step), `cuda` (a batched torch step on the GPU, each
            model's key/value pool allocated there for --max-sessions sessions up front) or `auto` (`cuda` when
            torch sees a GPU, else `cpu`).
        precision: The arithmetic of the native step's block products: `fp32` (exact: the reference's answers) or
            `bf16` (bfloat16 products on a CPU with AVX-512 BF16: about a third less engine time per act, actions
            within ~2e-3 of fp32's; docs/performance.md). Models the native step does not serve (image or
            full-attention models) and the naive server keep fp32; `gmt serve` refuses it with a GPU device or a
            native step built without AVX-512 BF16.
        naive: Serve by the reference path: full recompute, one request at a time, no batching (the exactness
            oracle and the baseline of every benchmark).
        replica_id: This process's name in a cluster, sent with every answer (REST header `X-Served-By`, gRPC
            initial metadata `x-served-by`) so that routing can be checked.
        record_dir: Where recorded sessions are written when they close or expire (`<session id>.npz` and
            `.json`, docs/records.md); replicas sharing a Redis store should share it. None: sessions cannot
            record.
        record_share: Share of new sessions recorded without asking (drawn from the session id), with record_dir.
        record_max_steps: Steps a recording keeps at most; past them the session goes on unrecorded.
    """

    model_config = SettingsConfigDict(env_prefix="GMT_", extra="ignore")

    checkpoints: Annotated[list[Path], NoDecode] = Field(default_factory=lambda: [Path("checkpoints")])
    host: str = "127.0.0.1"
    rest_port: int = Field(8000, ge=0, le=65535)
    grpc_port: int = Field(50051, ge=0, le=65535)
    max_sessions: int = Field(1024, ge=1)
    idle_timeout_s: float = Field(600.0, gt=0)
    batch_wait_ms: float = Field(2.0, ge=0)
    max_batch: int = Field(64, ge=1)
    inference_threads: int = Field(1, ge=1)
    call_threads: int = Field(2, ge=1, le=64)
    max_request_bytes: int = Field(1 << 20, ge=1024)
    auth_token: SecretStr | None = None
    auth_tokens: Path | None = None
    admin_token: SecretStr | None = None
    redis_url: str | None = None
    store_min_replicas: int = Field(0, ge=0)
    store_wait_timeout_s: float = Field(1.0, gt=0, le=4.0)
    store_spin_us: int = Field(0, ge=0, le=5000)
    log_format: Literal["json", "kv"] = "json"
    log_level: str = "INFO"
    shutdown_grace_s: float = Field(5.0, ge=0)
    keep_alive_s: float = Field(75.0, ge=1)
    header_timeout_s: float = Field(10.0, gt=0)
    body_timeout_s: float = Field(30.0, gt=0)
    body_min_rate: int = Field(500, ge=0)
    rest_max_connections: int = Field(0, ge=0)
    rest_max_connections_per_peer: int = Field(0, ge=0)
    grpc_max_connections: int = Field(0, ge=0)
    grpc_handshake_timeout_s: float = Field(10.0, gt=0)
    grpc_window_bytes: int = Field(64 * 1024, ge=1024, le=(1 << 31) - 1)
    grpc_max_streams_per_connection: int = Field(1024, ge=1)
    grpc_max_concurrent_rpcs: int = Field(2048, ge=1)
    grpc_write_timeout_s: float = Field(30.0, gt=0)
    event_loop: Literal["uvloop", "asyncio"] = "uvloop"
    device: str = Field("cpu", pattern=r"^(cpu|auto|cuda(:\d+)?)$")
    precision: Literal["fp32", "bf16"] = "fp32"
    naive: bool = False
    replica_id: str = Field(default_factory=lambda: f"{socket.gethostname()}:{os.getpid()}")  # hostname:pid
    record_dir: Path | None = None
    record_share: float = Field(0.0, ge=0.0, le=1.0)
    record_max_steps: int = Field(10_000, ge=1, le=MAX_RECORD_STEPS)

    @field_validator("checkpoints", mode="before")
    @classmethod
    def _split_paths(cls, v: object) -> object:
        if isinstance(v, str):
            return [p.strip() for p in v.split(",") if p.strip()]
        return v

    _keys: dict[str, str] = PrivateAttr(default_factory=dict)

    @field_validator("auth_token", "auth_tokens", "admin_token", "redis_url", "record_dir", mode="before")
    @classmethod
    def _empty_is_none(cls, v: object) -> object:
        return None if v == "" else v

    @field_validator("redis_url")
    @classmethod
    def _valid_store_url(cls, v: str | None) -> str | None:
        if v is not None:
            from gmt.service.redis_connect import parse_redis_url

            parse_redis_url(v)  # a ValueError naming the problem
        return v

    @model_validator(mode="after")
    def _read_keys(self) -> Settings:
        from gmt.service import keys

        file_keys = {} if self.auth_tokens is None else keys.read_key_file(self.auth_tokens)
        self._keys = keys.merge(file_keys, self.token)
        return self

    @model_validator(mode="after")
    def _share_needs_a_directory(self) -> Settings:
        if self.record_share and self.record_dir is None:
            raise ValueError("record_share needs record_dir: recorded sessions are written there")
        return self

    @model_validator(mode="after")
    def _replicas_need_redis(self) -> Settings:
        if self.store_min_replicas and not self.redis_url:
            raise ValueError(
                "store_min_replicas needs a Redis store (redis_url): sessions in memory have no replicas"
            )
        return self

    @field_validator("replica_id")
    @classmethod
    def _header_safe(cls, v: str) -> str:
        if not _REPLICA_ID.fullmatch(v):
            raise ValueError(
                f"replica_id must be 1 to 128 printable ASCII characters without spaces, got {v!r}"
            )
        return v

    @field_validator("log_level")
    @classmethod
    def _known_level(cls, v: str) -> str:
        if v.upper() not in ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL"):
            raise ValueError(f"log_level must be DEBUG, INFO, WARNING, ERROR or CRITICAL, got {v!r}")
        return v.upper()

    @property
    def token(self) -> str | None:
        """The bearer token in clear, or None when auth is off."""
        return self.auth_token.get_secret_value() if self.auth_token else None

    @property
    def keys(self) -> dict[str, str]:
        """The named keys in clear, name -> token (`auth_tokens` and `auth_token`); empty when auth is off."""
        return dict(self._keys)

    @property
    def management_token(self) -> str | None:
        """The bearer token of model management calls in clear (the admin token, else the auth token), or None."""
        return self.admin_token.get_secret_value() if self.admin_token else self.token


# Set in the environment (GMT_<NAME>) or by building `Settings`, not by `gmt serve` flags: knobs that tune or test
# the server rather than choose what it serves and to whom.
TUNING = frozenset(
    {
        "batch_wait_ms",
        "max_batch",
        "call_threads",
        "store_wait_timeout_s",
        "store_spin_us",
        "shutdown_grace_s",
        "keep_alive_s",
        "header_timeout_s",
        "body_timeout_s",
        "body_min_rate",
        "rest_max_connections",
        "rest_max_connections_per_peer",
        "grpc_max_connections",
        "grpc_handshake_timeout_s",
        "grpc_window_bytes",
        "grpc_max_streams_per_connection",
        "grpc_max_concurrent_rpcs",
        "grpc_write_timeout_s",
        "event_loop",
        "naive",
    }
)
