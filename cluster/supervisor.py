"""`gmt cluster up|down` (`make cluster` / `make cluster-down`): the scale-out topology, natively on loopback.

The session store has no single point of failure: a Redis primary (`redis`) and two replicas (`redis-replica`,
`redis-replica-2`, `--replicaof` the primary; AOF on, data under the run directory), watched by three sentinels
(`sentinel-1..3`, quorum 2) that promote a replica when the primary fails. Two `gmt serve` replicas (`gmt-1`,
`gmt-2`) reach the primary through the sentinels (`--redis-url redis+sentinel://...`) and acknowledge a step only
once a Redis replica holds it (`--store-min-replicas 1`); two Redis replicas, so that one is still there to
acknowledge after the other was promoted. nginx is in front with `cluster/nginx.conf` rendered for loopback
addresses: REST on :8000 and gRPC on :50051 by default (docs/cluster.md; `docker/compose.yaml` is the same
topology in containers). `up` returns once every process is ready (the Redis replicas in sync, the sentinels
agreeing on the primary and knowing each other and the replicas, nginx answering on both ports); each
process's pid is in `<run dir>/<name>.pid`, and `down` stops exactly those processes.

`upgrade` rolls a new model version through the running replicas: it loads the checkpoint on each (over each
replica's own REST port), promotes it on each, then drains the old default on each; sessions keep the version they
started with (docs/models.md).

The processes outlive the command that started them (each in a session of its own); their output goes to
`<run dir>/<name>.log`, nginx's to `<run dir>/nginx/error.log` and `access.log` (which replica served what).
"""

from __future__ import annotations

import collections
import json
import os
import random
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path

import typer

# Package data (pyproject.toml): `gmt cluster` runs from an installed wheel too.
NGINX_TEMPLATE = Path(__file__).with_name("nginx.conf")
DEFAULT_RUN_DIR = Path("run/cluster")
REPLICAS = ("gmt-1", "gmt-2")  # the default cluster's gmt replicas (`up(replicas=N)` names gmt-1 .. gmt-N)
REDIS_NODES = ("redis", "redis-replica", "redis-replica-2")  # the primary `up` starts, then its replicas
SENTINELS = ("sentinel-1", "sentinel-2", "sentinel-3")
SENTINEL_SERVICE = "gmt"  # the name the sentinels monitor the primary under
SENTINEL_QUORUM = 2
SENTINEL_DOWN_AFTER_MS = 1000  # a primary silent this long is down (for a sentinel; for all once 2 agree)
SENTINEL_FAILOVER_TIMEOUT_MS = 3000  # a failover that stalls is retried after twice this
INSTALL_HINT = "apt-get install nginx redis-server (.ci/run installs both)"
_PLACEHOLDER = re.compile(r"\$\{(GMT_[A-Z0-9_]+)\}")
# The order `down` stops them in: no new calls first, then the replicas (graceful), then the sentinels (so that
# stopping the primary starts no failover), the Redis servers last.
_STOP_ORDER = ("nginx", *(f"gmt-{i}" for i in range(1, 65)), *SENTINELS, *REDIS_NODES)

# Processes this Python process started: polled (and so reaped) instead of probed by pid.
_children: dict[int, subprocess.Popen] = {}


class ClusterError(RuntimeError):
    """The cluster could not be started or stopped; the message says why and where the logs are."""


@dataclass(frozen=True)
class Replica:
    """One `gmt serve` process of the cluster."""

    name: str
    pid: int
    rest_port: int
    grpc_port: int


@dataclass(frozen=True)
class Cluster:
    """A started cluster: where to reach it and which processes it is (also in `<run_dir>/cluster.json`)."""

    run_dir: Path
    rest_url: str
    grpc_target: str
    redis_url: str
    pids: dict[str, int]
    replicas: list[Replica] = field(default_factory=list)
    ports: dict[str, int] = field(default_factory=dict)  # of the Redis servers and the sentinels, by name

    def replica(self, name: str) -> Replica:
        """The replica with this id."""
        return next(r for r in self.replicas if r.name == name)

    def primary(self, timeout_s: float = 1.0) -> str | None:
        """The Redis server (`redis`, `redis-replica`, ...) that a majority of the sentinels name as the primary
        (None: no majority answers, or they name no server of this cluster)."""
        named = [_sentinel_primary(self.host, self.ports[s], timeout_s) for s in SENTINELS]
        by_port = {self.ports[n]: n for n in REDIS_NODES if n in self.ports}
        for port in {p for p in named if p is not None}:
            if named.count(port) >= SENTINEL_QUORUM:
                return by_port.get(port)
        return None

    @property
    def host(self) -> str:
        """The interface every process binds."""
        return self.grpc_target.rpartition(":")[0].strip("[]")


# ----- helpers -------------------------------------------------------------------------------------------------
def find_executable(name: str) -> str | None:
    """`name` on PATH, or in the sbin folders a non-root PATH often lacks (Debian installs nginx there)."""
    extra = os.pathsep.join(("/usr/sbin", "/usr/local/sbin", "/sbin"))
    return shutil.which(name) or shutil.which(name, path=extra)


_GIVEN: collections.deque[int] = collections.deque(maxlen=4096)  # ports free_port handed out lately


def _ephemeral_range() -> tuple[int, int]:
    """The kernel's range of local ports for outgoing connections (and for bind to port 0)."""
    try:
        lo, hi = map(int, Path("/proc/sys/net/ipv4/ip_local_port_range").read_text().split())
        return lo, hi
    except (OSError, ValueError):
        return 32768, 60999  # Linux's default


def free_port(host: str = "127.0.0.1") -> int:
    """A port nothing listens on right now (bound, then released), and not one handed out lately.

    The port is bound later by another process (Redis, a sentinel, nginx, a replica), seconds later for some.
    A port from bind(0) lies in the kernel's ephemeral range, where any outgoing connection may take it
    meanwhile as its local port ("Address already in use" at start); so it is drawn below that range.
    """
    lo, _ = _ephemeral_range()
    draw = random.SystemRandom()
    for _ in range(200 if lo > 11_000 else 0):
        port = draw.randrange(10_000, lo)
        if port in _GIVEN:
            continue
        with socket.socket() as s:
            try:
                s.bind((host, port))
            except OSError:
                continue
        _GIVEN.append(port)
        return port
    with socket.socket() as s:  # no room below the ephemeral range: the kernel's pick
        s.bind((host, 0))
        port = s.getsockname()[1]
    _GIVEN.append(port)
    return port


def _check_free(host: str, port: int, what: str) -> None:
    with socket.socket() as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError as e:
            raise ClusterError(f"{what} port {host}:{port} is taken ({e.strerror}); choose another") from None


_UPSTREAM_SERVER = re.compile(
    r"^(?P<indent>[ \t]*)server \$\{GMT_(?P<kind>REST|GRPC)_(?P<i>\d+)\}(?P<rest>.*)\n", re.M
)


def for_replicas(text: str, n: int) -> str:
    """`cluster/nginx.conf`'s text with each upstream's `server ${GMT_REST_i} ...` lines repeated for `n` replicas
    (the template, like `docker/compose.yaml`, names two)."""

    def block(m: re.Match) -> str:
        if m.group("i") != "1":
            return ""  # the first line of an upstream stands for all of them
        return "".join(
            f"{m.group('indent')}server ${{GMT_{m.group('kind')}_{i}}}{m.group('rest')}\n"
            for i in range(1, n + 1)
        )

    return _UPSTREAM_SERVER.sub(block, text)


def gmt_command() -> list[str]:
    """How to run `gmt` from this interpreter: its `gmt` script, else the module (an install without scripts,
    e.g. `pip install --target`)."""
    exe = Path(sys.executable).parent / "gmt"
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "gmt.service.cli"]


def render_nginx_conf(values: Mapping[str, str], template: Path = NGINX_TEMPLATE) -> str:
    """`cluster/nginx.conf` with every `${GMT_*}` placeholder replaced by `values[name]`.

    Raises:
        ClusterError: a placeholder without a value (or a value for no placeholder).
    """
    replicas = sum(1 for k in values if k.startswith("GMT_REST_") and k[len("GMT_REST_") :].isdigit())
    text = for_replicas(template.read_text(), replicas) if replicas else template.read_text()
    names = set(_PLACEHOLDER.findall(text))
    missing, unknown = sorted(names - set(values)), sorted(set(values) - names)
    if missing or unknown:
        raise ClusterError(f"{template}: placeholders without a value {missing}, values for none {unknown}")
    return _PLACEHOLDER.sub(lambda m: str(values[m.group(1)]), text)


def nginx_values(
    run_dir: Path,
    host: str,
    rest_port: int,
    grpc_port: int,
    replicas: Sequence[tuple[int, int]],
) -> dict[str, str]:
    """The template's values for a loopback cluster: nginx on (rest_port, grpc_port), replicas' (REST, gRPC).

    The template names two replicas (`docker/compose.yaml` runs two); `for_replicas` adapts it to any number."""
    if not replicas:
        raise ClusterError("a cluster needs at least one gmt replica")
    nginx_dir = (run_dir / "nginx").resolve()
    h = f"[{host}]" if ":" in host else host
    values = {
        "GMT_NGINX_REST_LISTEN": f"{h}:{rest_port}",
        "GMT_NGINX_GRPC_LISTEN": f"{h}:{grpc_port}",
        "GMT_NGINX_RUN_DIR": str(nginx_dir),
        "GMT_NGINX_ERROR_LOG": str(nginx_dir / "error.log"),
        "GMT_NGINX_ACCESS_LOG": str(nginx_dir / "access.log"),
    }
    for i, (rest, grpc) in enumerate(replicas, start=1):
        values[f"GMT_REST_{i}"] = f"{h}:{rest}"
        values[f"GMT_GRPC_{i}"] = f"{h}:{grpc}"
    return values


def nginx_test(conf: Path, nginx: str | None = None) -> subprocess.CompletedProcess:
    """`nginx -t` on a rendered config (its prefix is the config's folder)."""
    exe = nginx or find_executable("nginx")
    if exe is None:
        raise ClusterError(f"nginx is not installed ({INSTALL_HINT})")
    prefix = conf.resolve().parent
    return subprocess.run(
        [exe, "-t", "-p", str(prefix), "-c", str(conf.resolve()), "-e", str(prefix / "error.log")],
        capture_output=True,
        text=True,
        timeout=30,
    )


def _cmdline(pid: int) -> str | None:
    """The process's command line ('' where /proc is missing), None when no such process."""
    proc = Path(f"/proc/{pid}")
    if not Path("/proc/self").exists():
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return None
        except PermissionError:
            pass
        return ""
    try:
        status = (proc / "status").read_text()
        if re.search(r"^State:\s+Z", status, flags=re.M):
            return None  # a zombie: it has exited
        return (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError):
        return None


def _alive(pid: int) -> bool:
    child = _children.get(pid)
    if child is not None:
        return child.poll() is None
    return _cmdline(pid) is not None


def _is_ours(name: str, pid: int) -> bool:
    """Whether `pid` is still the process `name` was (pids are reused): its command line says so."""
    cmd = _cmdline(pid)
    if cmd is None:
        return False
    if cmd == "":
        return True  # no /proc: trust the pid file
    if name in REDIS_NODES or name in SENTINELS:
        return "redis-server" in cmd or "redis-sentinel" in cmd
    if name == "nginx":
        return "nginx" in cmd
    return "serve" in cmd and name in cmd


def _read_pids(run_dir: Path) -> dict[str, int]:
    pids = {}
    for f in sorted(run_dir.glob("*.pid")):
        try:
            pids[f.stem] = int(f.read_text().strip())
        except ValueError:
            f.unlink()
    return pids


def _log_tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except FileNotFoundError:
        return "(no log)"


# ----- up / down -----------------------------------------------------------------------------------------------
def _spawn(name: str, cmd: list[str], run_dir: Path, env: Mapping[str, str] | None = None) -> int:
    log = open(run_dir / f"{name}.log", "ab")  # noqa: SIM115 - handed to the child
    try:
        proc = subprocess.Popen(
            cmd,
            stdin=subprocess.DEVNULL,
            stdout=log,
            stderr=subprocess.STDOUT,
            env=dict(env) if env is not None else None,
            start_new_session=True,  # outlives `gmt cluster up`; Ctrl-C in that terminal does not reach it
        )
    finally:
        log.close()
    _children[proc.pid] = proc
    (run_dir / f"{name}.pid").write_text(f"{proc.pid}\n")
    return proc.pid


def _redis_ping(host: str, port: int) -> bool:
    try:
        with socket.create_connection((host, port), timeout=1) as s:
            s.sendall(b"PING\r\n")
            return s.recv(64).startswith(b"+PONG")
    except OSError:
        return False


def _redis(host: str, port: int, timeout_s: float = 1.0):
    import redis

    return redis.Redis(host=host, port=port, socket_timeout=timeout_s, socket_connect_timeout=timeout_s)


def _replica_in_sync(host: str, port: int, primary_port: int) -> bool:
    """The replica at `port` is linked to its primary, the primary counts it online, and a write to the primary is
    acknowledged by its replicas (WAIT): only then does a write with `--store-min-replicas` succeed."""
    import redis

    try:
        with _redis(host, port) as r:
            info = r.info("replication")
        with _redis(host, primary_port) as r:
            replicas = [v for k, v in r.info("replication").items() if re.fullmatch(r"slave\d+", k)]
    except redis.RedisError:
        return False
    online = any(int(v.get("port", 0)) == port and v.get("state") == "online" for v in replicas)
    if not (info.get("role") == "slave" and info.get("master_link_status") == "up" and online):
        return False
    try:  # and it acknowledges writes: WAIT counts it (seen: "online" a few hundred ms before it does)
        with _redis(host, primary_port) as r:
            r.set("gmt:replication-probe", b"1", px=1000)
            return int(r.execute_command("WAIT", len(replicas), 200)) >= len(replicas)
    except redis.RedisError:
        return False


def _sentinel_primary(host: str, port: int, timeout_s: float = 1.0) -> int | None:
    """The port of the primary this sentinel names (None: it names none, or does not answer)."""
    import redis

    try:
        with _redis(host, port, timeout_s) as r:
            addr = r.sentinel_get_master_addr_by_name(SENTINEL_SERVICE)
    except redis.RedisError:
        return None
    return int(addr[1]) if addr else None


def _sentinel_ready(host: str, port: int, primary_port: int, replicas: int) -> bool:
    """This sentinel sees the primary up, with every replica and the other two sentinels."""
    import redis

    try:
        with _redis(host, port) as r:
            m = r.sentinel_master(SENTINEL_SERVICE)
    except redis.RedisError:
        return False
    return (
        int(m["port"]) == primary_port
        and m["is_master"]
        and not (m["is_sdown"] or m["is_odown"])
        and m["num-slaves"] == replicas
        and m["num-other-sentinels"] == len(SENTINELS) - 1
    )


def sentinel_conf(host: str, port: int, primary_port: int, work_dir: Path) -> str:
    """A sentinel's config file: loopback only, quorum 2, a primary silent for 1 s is down, short failovers."""
    s = SENTINEL_SERVICE
    return "\n".join(
        [
            f"bind {host}",
            f"port {port}",
            "daemonize no",
            f"dir {work_dir.resolve()}",  # sentinels rewrite their config file (what they learn) here
            f"sentinel monitor {s} {host} {primary_port} {SENTINEL_QUORUM}",
            f"sentinel down-after-milliseconds {s} {SENTINEL_DOWN_AFTER_MS}",
            f"sentinel failover-timeout {s} {SENTINEL_FAILOVER_TIMEOUT_MS}",
            f"sentinel parallel-syncs {s} 1",
            "",
        ]
    )


def _http_ready(url: str) -> bool:
    import httpx

    try:
        return httpx.get(url, timeout=2).status_code == 200
    except httpx.HTTPError:
        return False


def _grpc_ready(target: str) -> bool:
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    try:
        with grpc.insecure_channel(target) as ch:
            r = health_pb2_grpc.HealthStub(ch).Check(health_pb2.HealthCheckRequest(), timeout=2)
            return r.status == health_pb2.HealthCheckResponse.SERVING
    except grpc.RpcError:
        return False


def _wait(what: str, ready, pid: int, log: Path, deadline: float) -> None:
    while not ready():
        if not _alive(pid):
            raise ClusterError(f"{what} exited while starting; the end of {log}:\n{_log_tail(log)}")
        if time.monotonic() > deadline:
            raise ClusterError(f"{what} was not ready in time; the end of {log}:\n{_log_tail(log)}")
        time.sleep(0.2)


def up(
    run_dir: Path = DEFAULT_RUN_DIR,
    *,
    host: str = "127.0.0.1",
    rest_port: int = 8000,
    grpc_port: int = 50051,
    redis_port: int = 0,
    store_min_replicas: int = 1,
    replicas: int = len(REPLICAS),
    checkpoints: Sequence[Path] = (),
    serve_args: Sequence[str] = (),
    env: Mapping[str, str] | None = None,
    timeout_s: float = 180.0,
    template: Path = NGINX_TEMPLATE,
) -> Cluster:
    """Start the Redis servers, the sentinels, the replicas and nginx; return once all are ready.

    Args:
        run_dir: Pid files, logs, Redis data (AOF), sentinel configs and nginx's files.
        host: The loopback (or other) interface every process binds.
        rest_port / grpc_port: Where nginx listens (0 = a free port).
        redis_port: The Redis primary's port (0 = a free port); the other ports are always free ones.
        store_min_replicas: Each replica's `--store-min-replicas` (Redis replicas that must hold a step before
            it is acknowledged; at most the two there are).
        replicas: gmt serve replicas behind nginx (`gmt-1` .. `gmt-N`; 2 by default, as in docker/compose.yaml).
        checkpoints: Passed to each replica as --checkpoints (none: its default, GMT_CHECKPOINTS or checkpoints/).
        serve_args: More `gmt serve` flags for both replicas (e.g. ["--record-dir", "recordings"]; tuning
            knobs such as GMT_BATCH_WAIT_MS go in `env`).
        env: The replicas' environment (default: this process's; GMT_* variables apply where no flag is given).
        timeout_s: Longest wait for everything to be ready.

    Raises:
        ClusterError: a program is missing, a port is taken, a cluster already runs in `run_dir`, or a process
            failed to start (everything started so far is stopped again).
    """
    redis_exe, nginx_exe = find_executable("redis-server"), find_executable("nginx")
    missing = [n for n, exe in (("redis-server", redis_exe), ("nginx", nginx_exe)) if exe is None]
    if missing:
        raise ClusterError(f"{' and '.join(missing)} not installed ({INSTALL_HINT})")
    if not 0 <= store_min_replicas < len(REDIS_NODES):
        raise ClusterError(
            f"store_min_replicas must be 0 to {len(REDIS_NODES) - 1}, got {store_min_replicas}"
        )
    run_dir = Path(run_dir)
    running = [n for n, pid in _read_pids(run_dir).items() if _is_ours(n, pid)] if run_dir.exists() else []
    if running:
        raise ClusterError(f"a cluster already runs from {run_dir} ({', '.join(running)}); stop it first")
    for f in run_dir.glob("*.pid"):
        f.unlink()  # stale
    for name in (*REDIS_NODES, *SENTINELS, "nginx"):
        (run_dir / name).mkdir(parents=True, exist_ok=True)
    rest_port = rest_port or free_port(host)
    grpc_port = grpc_port or free_port(host)
    _check_free(host, rest_port, "REST (nginx)")
    _check_free(host, grpc_port, "gRPC (nginx)")
    redis_port = redis_port or free_port(host)
    _check_free(host, redis_port, "Redis")
    ports = {"redis": redis_port} | {n: free_port(host) for n in (*REDIS_NODES[1:], *SENTINELS)}
    if not 1 <= replicas <= 64:
        raise ClusterError(f"replicas must be 1 to 64, got {replicas}")
    names = [f"gmt-{i}" for i in range(1, replicas + 1)]
    gmt_ports = [(free_port(host), free_port(host)) for _ in names]
    h = f"[{host}]" if ":" in host else host
    redis_url = f"redis+sentinel://{','.join(f'{h}:{ports[n]}' for n in SENTINELS)}/{SENTINEL_SERVICE}"
    deadline = time.monotonic() + timeout_s
    pids: dict[str, int] = {}
    try:
        for name in REDIS_NODES:
            cmd = [
                redis_exe,
                "--bind", host,
                "--port", str(ports[name]),
                "--dir", str((run_dir / name).resolve()),
                "--appendonly", "yes",
                "--appendfsync", "everysec",
                "--save", "",
                "--repl-diskless-sync-delay", "0",  # a replica's full sync starts at once (default: after 5 s)
                "--daemonize", "no",
            ]  # fmt: skip
            if name != "redis":
                cmd += ["--replicaof", host, str(redis_port)]
            pids[name] = _spawn(name, cmd, run_dir)
        for name in REDIS_NODES:
            ready = (
                (lambda: _redis_ping(host, redis_port))
                if name == "redis"
                else (lambda n=name: _replica_in_sync(host, ports[n], redis_port))
            )
            _wait(name, ready, pids[name], run_dir / f"{name}.log", deadline)
        # Started once the replicas are in sync: a sentinel learns them from the primary's first INFO answer.
        for name in SENTINELS:
            conf = run_dir / name / "sentinel.conf"
            conf.write_text(sentinel_conf(host, ports[name], redis_port, run_dir / name))
            pids[name] = _spawn(name, [redis_exe, str(conf.resolve()), "--sentinel"], run_dir)

        gmt = gmt_command()
        ckpt = [a for c in checkpoints for a in ("--checkpoints", str(c))]
        started = []
        for name, (rest, grpc_) in zip(names, gmt_ports, strict=True):
            cmd = [*gmt, "serve", "--replica-id", name, "--host", host, "--rest-port", str(rest)]
            cmd += ["--grpc-port", str(grpc_), "--redis-url", redis_url]
            cmd += ["--store-min-replicas", str(store_min_replicas), *ckpt, *serve_args]
            pids[name] = _spawn(name, cmd, run_dir, env)
            started.append(Replica(name, pids[name], rest, grpc_))

        conf = run_dir / "nginx" / "nginx.conf"
        conf.write_text(
            render_nginx_conf(nginx_values(run_dir, host, rest_port, grpc_port, gmt_ports), template)
        )
        nginx_dir = (run_dir / "nginx").resolve()
        cmd = [nginx_exe, "-p", str(nginx_dir), "-c", str(conf.resolve()), "-e", str(nginx_dir / "error.log")]
        pids["nginx"] = _spawn("nginx", [*cmd, "-g", "daemon off;"], run_dir)

        replica_count = len(REDIS_NODES) - 1
        for name in SENTINELS:
            ready = lambda n=name: _sentinel_ready(host, ports[n], redis_port, replica_count)  # noqa: E731
            _wait(name, ready, pids[name], run_dir / f"{name}.log", deadline)
        for r in started:
            log = run_dir / f"{r.name}.log"
            _wait(r.name, lambda r=r: _http_ready(f"http://{h}:{r.rest_port}/readyz"), r.pid, log, deadline)
        rest_url, grpc_target = f"http://{h}:{rest_port}", f"{h}:{grpc_port}"
        log = run_dir / "nginx" / "error.log"
        _wait("nginx (REST)", lambda: _http_ready(f"{rest_url}/readyz"), pids["nginx"], log, deadline)
        _wait("nginx (gRPC)", lambda: _grpc_ready(grpc_target), pids["nginx"], log, deadline)
    except BaseException:
        down(run_dir, quiet=True)
        raise
    cluster = Cluster(run_dir, rest_url, grpc_target, redis_url, pids, started, ports)
    state = {**asdict(cluster), "run_dir": str(run_dir)}
    (run_dir / "cluster.json").write_text(json.dumps(state, indent=2) + "\n")
    return cluster


def _signal(pid: int, sig: int) -> None:
    try:
        os.kill(pid, sig)
    except ProcessLookupError:
        pass


def down(run_dir: Path = DEFAULT_RUN_DIR, *, timeout_s: float = 15.0, quiet: bool = False) -> dict[str, str]:
    """Stop the processes named by `<run_dir>/*.pid` (graceful signal, SIGKILL after `timeout_s`).

    A pid whose process is gone, or is now some other program (its command line says so), is not signalled.

    Returns:
        What happened to each: "stopped", "killed", "not running" or "not ours".
    """
    run_dir = Path(run_dir)
    pids = _read_pids(run_dir) if run_dir.exists() else {}
    order = sorted(pids, key=lambda n: _STOP_ORDER.index(n) if n in _STOP_ORDER else len(_STOP_ORDER))
    outcome: dict[str, str] = {}
    # nginx first (no new calls), then every replica at once (graceful, GMT_SHUTDOWN_GRACE_S), the sentinels
    # (no failover while the Redis servers stop), the Redis servers last.
    store = (*SENTINELS, *REDIS_NODES)
    groups = (
        ["nginx"],
        [n for n in order if n != "nginx" and n not in store],
        list(SENTINELS),
        list(REDIS_NODES),
    )
    for group in groups:
        live = {}
        for name in (n for n in group if n in pids):
            pid = pids[name]
            if not _alive(pid):
                outcome[name] = "not running"
            elif not _is_ours(name, pid):
                outcome[name] = "not ours"
            else:
                _signal(pid, signal.SIGQUIT if name == "nginx" else signal.SIGTERM)
                live[name] = pid
        end = time.monotonic() + timeout_s
        while live and time.monotonic() < end:
            for name in [n for n, p in live.items() if not _alive(p)]:
                outcome[name] = "stopped"
                del live[name]
            time.sleep(0.05)
        for name, pid in live.items():
            _signal(pid, signal.SIGKILL)
            outcome[name] = "killed"
            deadline = time.monotonic() + 5
            while _alive(pid) and time.monotonic() < deadline:
                time.sleep(0.05)
        for name in group:
            if name in pids:
                (run_dir / f"{name}.pid").unlink(missing_ok=True)
                _children.pop(pids[name], None)
    if not quiet:
        for name in order:
            typer.echo(f"{name}: {outcome.get(name, 'not running')}", err=True)
    return outcome


# ----- rolling upgrade -----------------------------------------------------------------------------------------
def load_cluster(run_dir: Path = DEFAULT_RUN_DIR) -> Cluster:
    """The cluster `up` started from `run_dir` (its `cluster.json`).

    Raises:
        ClusterError: no cluster was started there.
    """
    state = Path(run_dir) / "cluster.json"
    try:
        d = json.loads(state.read_text())
    except FileNotFoundError:
        raise ClusterError(
            f"no cluster runs from {run_dir} (no {state}); start one with `gmt cluster up`"
        ) from None
    d["run_dir"] = Path(d["run_dir"])
    d["replicas"] = [Replica(**r) for r in d["replicas"]]
    return Cluster(**d)


def replica_urls(c: Cluster) -> dict[str, str]:
    """Each replica's own REST base URL (not through nginx), by replica name."""
    h = f"[{c.host}]" if ":" in c.host else c.host
    return {r.name: f"http://{h}:{r.rest_port}" for r in c.replicas}


@dataclass
class UpgradeReport:
    """What `upgrade` did.

    Attributes:
        version: The new version.
        old: The default version each replica had before, by replica.
        done: Replicas that load, promote and drain all succeeded on.
        failed: Replicas that could not be upgraded, with why (unreachable, or the server's refusal).
    """

    model: str
    version: str = ""
    old: dict[str, str] = field(default_factory=dict)
    done: list[str] = field(default_factory=list)
    failed: dict[str, str] = field(default_factory=dict)


def upgrade(
    checkpoint: Path,
    run_dir: Path = DEFAULT_RUN_DIR,
    *,
    model: str | None = None,
    token: str | None = None,
    progress=None,
) -> UpgradeReport:
    """Roll a checkpoint through the cluster's replicas as the new default version of `model`: load it on every
    replica, then promote it on every replica, then drain each replica's old default. A replica that fails a step
    (killed, say) is reported and left out of the later steps; the others go on, and its sessions move to them
    (they load their version by fingerprint where they lack it).

    Args:
        checkpoint: The checkpoint directory; it must be under the replicas' checkpoint roots.
        model: The model name (default: the only model the replicas serve).
        token: The replicas' admin token (else their auth token; none: the replicas are on this machine).
        progress: Called with (step, replica, detail) after each step on each replica ("load", "promote", "drain").

    Raises:
        ClusterError: no cluster in `run_dir`, no replica answers, the model is ambiguous, or the replicas loaded
            different versions (another checkpoint under the same path on one of them).
    """
    from gmt.client.errors import ServiceError
    from gmt.client.models import AdminClient

    c = load_cluster(run_dir)
    path = str(Path(checkpoint).resolve())
    clients = {n: AdminClient(u, token) for n, u in replica_urls(c).items()}
    report = UpgradeReport(model or "")
    live: list[str] = []
    try:
        for name, client in clients.items():
            try:
                served = {m["name"]: m for m in client.models()}
            except ServiceError as e:
                report.failed[name] = str(e)
                continue
            if not report.model:
                if len(served) != 1:
                    raise ClusterError(
                        f"{name} serves {sorted(served) or 'no model'}: name the model (--model)"
                    )
                report.model = next(iter(served))
            if report.model not in served:
                report.failed[name] = f"does not serve model {report.model!r}"
                continue
            report.old[name] = served[report.model]["default_version"]
            live.append(name)
        if not live:
            raise ClusterError(f"no replica could be upgraded: {report.failed}")

        def run_step(step: str, client, name: str) -> str:
            if step == "load":
                return client.load(report.model, path)["version"]
            if step == "promote":
                client.promote(report.model, report.version)
                return report.version
            if report.old[name] == report.version:
                return "nothing to drain"
            client.drain(report.model, report.old[name])
            return report.old[name]

        for step in ("load", "promote", "drain"):
            for name in list(live):
                try:
                    detail = run_step(step, clients[name], name)
                except ServiceError as e:
                    report.failed[name] = f"{step}: {e}"
                    live.remove(name)
                    continue
                if step == "load":
                    if report.version and detail != report.version:
                        raise ClusterError(
                            f"{name} loaded version {detail}, another replica {report.version}"
                        )
                    report.version = detail
                if progress is not None:
                    progress(step, name, detail)
        report.done = live
    finally:
        for client in clients.values():
            client.http.close()
    return report


# ----- the command ---------------------------------------------------------------------------------------------
app = typer.Typer(
    help="The scale-out topology on loopback: Redis with Sentinel, two gmt serve replicas and nginx.",
    no_args_is_help=True,
)


@app.command("up", context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
def up_command(
    ctx: typer.Context,
    run_dir: Path = typer.Option(
        DEFAULT_RUN_DIR, help="Pid files, logs, Redis data, sentinel and nginx files."
    ),
    host: str = typer.Option("127.0.0.1", help="Interface every process binds."),
    rest_port: int = typer.Option(8000, help="nginx's REST port (0 = any free port)."),
    grpc_port: int = typer.Option(50051, help="nginx's gRPC port (0 = any free port)."),
    redis_port: int = typer.Option(0, help="The Redis primary's port (0 = any free port)."),
    store_min_replicas: int = typer.Option(
        1, help="Redis replicas that must hold a step before a gmt replica acknowledges it (0, 1 or 2)."
    ),
    replicas: int = typer.Option(2, help="gmt serve replicas behind nginx (gmt-1 .. gmt-N)."),
    checkpoints: list[Path] = typer.Option(
        None, "--checkpoints", "-c", help="Checkpoints for both replicas (default: theirs, checkpoints/)."
    ),
    timeout: float = typer.Option(180.0, help="Longest wait, in seconds, for everything to be ready."),
) -> None:
    """Start the cluster and return once it is ready. More `gmt serve` flags for both replicas may follow
    (e.g. `-- --idle-timeout 60`; tuning knobs as GMT_* variables); GMT_* environment variables (GMT_AUTH_TOKEN, ...) reach the replicas."""
    try:
        c = up(
            run_dir,
            host=host,
            rest_port=rest_port,
            grpc_port=grpc_port,
            redis_port=redis_port,
            store_min_replicas=store_min_replicas,
            replicas=replicas,
            checkpoints=checkpoints or (),
            serve_args=list(ctx.args),
            timeout_s=timeout,
        )
    except ClusterError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"REST {c.rest_url}  gRPC {c.grpc_target}  (through nginx)")
    for r in c.replicas:
        typer.echo(f"{r.name}: pid {r.pid}, REST :{r.rest_port}, gRPC :{r.grpc_port}")
    for name in REDIS_NODES:
        typer.echo(f"{name}: pid {c.pids[name]}, :{c.ports[name]} (AOF in {run_dir}/{name})")
    for name in SENTINELS:
        typer.echo(f"{name}: pid {c.pids[name]}, :{c.ports[name]}")
    typer.echo(
        f"store: {c.redis_url} (primary: redis; acknowledged once {store_min_replicas} replica(s) hold it)"
    )
    typer.echo(f"nginx: pid {c.pids['nginx']}; pids in {run_dir}/*.pid, logs in {run_dir}/*.log")


@app.command("down")
def down_command(
    run_dir: Path = typer.Option(DEFAULT_RUN_DIR, help="The run directory `up` used."),
    timeout: float = typer.Option(15.0, help="Seconds each process gets to stop before SIGKILL."),
) -> None:
    """Stop exactly the processes whose pids `up` wrote to <run dir>/*.pid."""
    if not down(run_dir, timeout_s=timeout):
        typer.echo(f"nothing to stop: {run_dir} holds no pid file of `gmt cluster up`")


@app.command("upgrade")
def upgrade_command(
    checkpoint: Path = typer.Argument(
        ..., help="The new checkpoint directory (under the replicas' checkpoint roots)."
    ),
    model: str = typer.Option(None, help="Model name (default: the only model the replicas serve)."),
    run_dir: Path = typer.Option(DEFAULT_RUN_DIR, help="The run directory `up` used."),
    token: str = typer.Option(
        None,
        envvar=["GMT_ADMIN_TOKEN", "GMT_AUTH_TOKEN"],
        help="The replicas' admin token, else their auth token.",
    ),
) -> None:
    """Roll a new model version through the replicas: load it on each, promote it on each, drain the old one on
    each. Live sessions finish on the version they started with."""
    try:
        where = ", ".join(f"{n} {u}" for n, u in replica_urls(load_cluster(run_dir)).items())
        typer.echo(f"cluster {run_dir}: {where}")
        typer.echo(f"upgrading {model or 'the one model the replicas serve'} to {checkpoint}")
        r = upgrade(
            checkpoint,
            run_dir,
            model=model,
            token=token,
            progress=lambda step, name, detail: typer.echo(f"{name}: {step} {detail}"),
        )
    except ClusterError as e:
        typer.echo(f"error: {e}", err=True)
        raise typer.Exit(1) from None
    typer.echo(f"{r.model} {r.version} is the default on {', '.join(r.done) or 'no replica'}")
    for name, why in r.failed.items():
        typer.echo(f"error: {name} not upgraded: {why}", err=True)
    if r.failed:
        raise typer.Exit(1)
