"""What a user would deploy instead of `gmt serve`: the same checkpoint behind Ray Serve with `@serve.batch`.

Run as its own process by `gmt bench` (the `bench` extra installs Ray):

    python -m gmt.bench.ray_app CHECKPOINT PORT {recompute,incremental}

It serves `POST /sessions` ({"goal", "seed"} -> {"session_id"}) and `POST /sessions/{id}/act`
({"observation"} -> {"action"}) on 127.0.0.1:PORT through Ray Serve's HTTP proxy, prints `READY` once requests
are answered, and stops when its standard input closes. Acts of concurrent sessions are batched by
`@serve.batch` (up to 256, 2 ms wait) into one `PolicyEngine.act` call: `recompute` is the model's reference
forward over each window (what a user without our engine runs), `incremental` our key/value-cached engine.
"""

from __future__ import annotations

import sys
import uuid

import numpy as np
from fastapi import FastAPI
from ray import serve

app = FastAPI()


@serve.deployment(max_ongoing_requests=4096)
@serve.ingress(app)
class GMTDeployment:
    """One replica holding every session's context in its engine's pool."""

    def __init__(self, checkpoint: str, path: str) -> None:
        import torch

        from gmt.model.checkpoint import load_checkpoint
        from gmt.model.engine import PolicyEngine

        torch.set_num_threads(1)  # as `gmt serve`'s default inference_threads
        self.engine = PolicyEngine(load_checkpoint(checkpoint), incremental=path == "incremental")
        self.contexts: dict = {}

    @app.post("/sessions")
    async def create(self, body: dict) -> dict:
        sid = uuid.uuid4().hex
        self.contexts[sid] = self.engine.new_context(int(body.get("goal", 0)), seed=int(body.get("seed", 0)))
        return {"session_id": sid}

    @app.post("/sessions/{sid}/act")
    async def act(self, sid: str, body: dict) -> dict:
        action = await self._act((sid, body["observation"]))
        return {"action": np.asarray(action).tolist()}

    @serve.batch(max_batch_size=256, batch_wait_timeout_s=0.002)
    async def _act(self, items: list[tuple[str, list]]) -> list:
        contexts = [self.contexts[sid] for sid, _ in items]
        return self.engine.act(contexts, [np.asarray(o, dtype=np.float32) for _, o in items])


def main() -> None:
    import ray

    checkpoint, port, path = sys.argv[1], int(sys.argv[2]), sys.argv[3]
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, object_store_memory=256 * 2**20)
    serve.start(http_options={"host": "127.0.0.1", "port": port})
    serve.run(GMTDeployment.bind(checkpoint, path), route_prefix="/")
    print("READY", flush=True)
    sys.stdin.read()  # until the parent closes our stdin
    serve.shutdown()
    ray.shutdown()


if __name__ == "__main__":
    main()
