"""The containers for real (docs/cluster.md): the gmt image built by docker/image.sh on the local Debian base
(docker/local-images.sh: no registry is needed), docker/compose.yaml brought up by docker/compose.sh on free
loopback ports with Debian-built Redis and nginx images, a session driven through nginx, the gmt container serving
it killed mid-episode (and a gRPC Control stream's on the same replica), and each episode checked against an uninterrupted twin; then everything is removed.

Runs with docker or podman (podman-compose from the `dev` extra); skipped only where neither can run. Cheap when
warm: the base image is reused whenever present and the gmt image whenever its inputs are unchanged."""

from __future__ import annotations

import os
import secrets
import shutil
import stat
import subprocess
import tempfile
import time
from pathlib import Path

import grpc
import httpx
import numpy as np
import pytest
from container_engine import DOCKER, IMAGE, build_env, engine

from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient
from gmt.cluster.supervisor import free_port
from gmt.model.fixtures import tiny_checkpoint
from gmt.v1 import policy_pb2 as pb
from gmt.v1 import policy_pb2_grpc

MODEL = "tiny-cheetah"
STEPS, KILL_AT = 10, 4


ENGINE, WHY_NOT = engine()
pytestmark = pytest.mark.skipif(ENGINE is None, reason=f"no container engine can run: {WHY_NOT}")


def _run(*cmd: str, env: dict[str, str], timeout: float = 900) -> str:
    r = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, (
        f"{' '.join(cmd)} exited {r.returncode}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    )
    return r.stdout


class Topology:
    """A compose project started by docker/compose.sh: its environment, URLs and containers."""

    def __init__(self, env: dict[str, str]) -> None:
        self.env = env
        self.project = env["COMPOSE_PROJECT"]
        self.rest_url = f"http://127.0.0.1:{env['GMT_REST_PORT']}"
        self.grpc_target = f"127.0.0.1:{env['GMT_GRPC_PORT']}"
        self.token = env["GMT_AUTH_TOKEN"]

    def container(self, service: str) -> str:
        labels = [
            f"label=com.docker.compose.{k}={v}" for k, v in (("project", self.project), ("service", service))
        ]
        out = _run(
            ENGINE,
            "ps",
            "-a",
            "--filter",
            labels[0],
            "--filter",
            labels[1],
            "--format",
            "{{.Names}}",
            env=self.env,
        )
        return out.split()[0]

    def containers(self) -> list[str]:
        filt = f"label=com.docker.compose.project={self.project}"
        return _run(ENGINE, "ps", "-a", "--filter", filt, "--format", "{{.Names}}", env=self.env).split()


@pytest.fixture(scope="module")
def topology(prebuilt):
    env = build_env(ENGINE)
    t0 = time.monotonic()
    base, redis, nginx = _run(str(DOCKER / "local-images.sh"), env=env).split()
    t_local = time.monotonic() - t0
    _run(str(DOCKER / "image.sh"), env={**env, "IMAGE": IMAGE, "BASE": base}, timeout=1800)
    t_image = time.monotonic() - t0 - t_local
    # The replicas run as an unprivileged user: the checkpoints must be readable by anyone (pytest's tmp_path
    # folders are private).
    checkpoints = Path(tempfile.mkdtemp(prefix="gmt-compose-ckpt-"))
    checkpoints.chmod(0o755)
    tiny_checkpoint(checkpoints / MODEL, name=MODEL, attention="window", calibrated=True)
    for p in checkpoints.rglob("*"):
        p.chmod(p.stat().st_mode | stat.S_IROTH | (stat.S_IXOTH if p.is_dir() else 0))
    env.update(
        COMPOSE_PROJECT=f"gmt-test-{os.getpid()}",
        GMT_IMAGE=IMAGE,
        GMT_REDIS_IMAGE=redis,
        GMT_NGINX_IMAGE=nginx,
        GMT_CHECKPOINTS_DIR=str(checkpoints),
        GMT_REST_PORT=str(free_port()),
        GMT_GRPC_PORT=str(free_port()),
        GMT_AUTH_TOKEN=secrets.token_hex(16),
    )
    topology = Topology(env)
    try:
        t1 = time.monotonic()
        _run(str(DOCKER / "compose.sh"), "up", env=env)
        print(
            f"\nlocal images {t_local:.1f} s, gmt image {t_image:.1f} s, compose up {time.monotonic() - t1:.1f} s"
        )
        yield topology
    finally:
        _run(str(DOCKER / "compose.sh"), "down", env=env)
        shutil.rmtree(checkpoints, ignore_errors=True)
    assert topology.containers() == []  # compose down left nothing, running or stopped


def rest_replica(http: httpx.Client, sid: str) -> str:
    return http.get(f"/sessions/{sid}").headers["x-served-by"]


def grpc_replica(stub, sid: str, token: str) -> str:
    metadata = (("x-session-id", sid), ("authorization", f"Bearer {token}"))
    _, call = stub.GetSession.with_call(pb.GetSessionRequest(session_id=sid), metadata=metadata)
    return dict(call.initial_metadata())["x-served-by"]


def test_the_stack_is_up_behind_nginx(topology):
    names = topology.containers()
    services = ("redis", "redis-replica", "redis-replica-2", "sentinel-1", "sentinel-2", "sentinel-3")
    assert len(names) == len(services) + 3, names
    with httpx.Client(base_url=topology.rest_url, timeout=30) as http:
        assert http.get("/models").status_code == 401  # the token is required through nginx
        auth = {"Authorization": f"Bearer {topology.token}"}
        r = http.get("/models", headers=auth)
        assert r.status_code == 200 and [m["name"] for m in r.json()["models"]] == [MODEL]
        assert r.headers["x-served-by"] in ("gmt-1", "gmt-2")
    user = _run(ENGINE, "exec", topology.container("gmt-1"), "id", "-u", env=topology.env).strip()
    assert user != "0"  # the replicas do not run as root


def test_the_gmt_container_serving_sessions_killed_mid_episode(topology):
    """A REST session and a gRPC Control stream on one replica; its container is killed (SIGKILL) after step
    KILL_AT - 1 and both episodes finish on the other replica, every action equal to an uninterrupted twin's."""
    rng = np.random.default_rng(7)
    obs = {"rest": rng.normal(size=(STEPS, 17)), "grpc": rng.normal(size=(STEPS, 17))}
    seeds = {"rest": 5, "grpc": 6}
    kw = dict(token=topology.token, retries=6, backoff_s=0.2)
    with (
        RestClient(topology.rest_url, **kw) as rest,
        GrpcClient(topology.grpc_target, stream=True, **kw) as streams,
        httpx.Client(
            base_url=topology.rest_url, timeout=30, headers={"Authorization": f"Bearer {topology.token}"}
        ) as http,
        grpc.insecure_channel(topology.grpc_target) as channel,
    ):
        stub = policy_pb2_grpc.PolicyServiceStub(channel)
        clients = {"rest": rest, "grpc": streams}
        want = {}
        for kind, client in clients.items():  # the twins: the same seeds and observations, nothing killed
            with client.create_session(MODEL, 1, seed=seeds[kind]) as twin:
                want[kind] = [twin.act(o).action for o in obs[kind]]
        sessions = {"rest": rest.create_session(MODEL, 1, seed=seeds["rest"])}
        victim = rest_replica(http, sessions["rest"].id)
        for _ in range(20):  # a gRPC session on the same replica (nginx hashes its id)
            s = streams.create_session(MODEL, 1, seed=seeds["grpc"])
            if grpc_replica(stub, s.id, topology.token) == victim:
                sessions["grpc"] = s
                break
            s.close()
        assert "grpc" in sessions, f"no gRPC session was routed to {victim}"
        got = {kind: [s.act(o) for o in obs[kind][:KILL_AT]] for kind, s in sessions.items()}
        _run(ENGINE, "kill", topology.container(victim), env=topology.env)  # SIGKILL, mid-episode
        for kind, s in sessions.items():
            got[kind] += [s.act(o) for o in obs[kind][KILL_AT:]]
        where = {
            "rest": rest_replica(http, sessions["rest"].id),
            "grpc": grpc_replica(stub, sessions["grpc"].id, topology.token),
        }
        steps = {kind: s.refresh().step for kind, s in sessions.items()}
        for s in sessions.values():
            s.close()
    survivor = ({"gmt-1", "gmt-2"} - {victim}).pop()
    assert where == {"rest": survivor, "grpc": survivor}  # the rest of each episode ran on the other replica
    assert steps == {"rest": STEPS, "grpc": STEPS}
    for kind in sessions:
        assert [r.step for r in got[kind]] == list(range(STEPS)), kind
        for t, (g, w) in enumerate(zip(got[kind], want[kind], strict=True)):
            np.testing.assert_array_equal(g.action, w, err_msg=f"{kind} step {t}")
        assert len({tuple(w) for w in want[kind]}) == STEPS  # sampled actions: the seed mattered
