"""Drive one session of a remote GMT server over REST and over gRPC with the thin client install alone.

    pip install gmt-service            # numpy, httpx, grpcio, protobuf, gymnasium, typer: no torch
    python remote_session.py --rest http://localhost:8000 --grpc localhost:50051

For each transport: pick the server's first model (or --model), open a session on its lowest goal with a fixed
seed, send `--steps` observations (zeros of the model's observation shape; a real client sends its sensors),
switch to the highest goal halfway, read the session back and close it. Both transports must answer the same
actions for the same seed and observations; the script prints one line per transport and exits 1 otherwise.
Nothing here needs an environment: see `gmt run` (and the `run` extra) to step a Gymnasium one.
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from gmt.client.base import PolicyClient
from gmt.client.grpc import GrpcClient
from gmt.client.rest import RestClient


def drive(client: PolicyClient, model: str | None, steps: int, seed: int) -> np.ndarray:
    """One episode of `steps` acts with a goal switch halfway; returns the actions, [steps, ...]."""
    spec = client.get_model(model) if model else client.list_models()[0]
    low, high = min(spec.goals, key=lambda g: g.mean), max(spec.goals, key=lambda g: g.mean)
    obs = np.zeros(spec.observation_space["shape"], dtype=np.float32)
    actions = []
    with client.create_session(spec.name, low.id, seed=seed) as session:
        for t in range(steps):
            if t == steps // 2:
                session.set_goal(high.name)
            r = session.act(obs)
            assert r.step == t and r.goal == (low.id if t < steps // 2 else high.id), (t, r)
            actions.append(np.asarray(r.action, dtype=np.float64))
        info = session.refresh()
        assert info.step == steps and info.goal == high.id, info
    return np.stack(actions)


def main(argv: list[str] | None = None) -> int:
    """Run both transports; 0 when they agree."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rest", default="http://localhost:8000", help="REST base URL")
    p.add_argument("--grpc", default="localhost:50051", help="gRPC host:port")
    p.add_argument("--model", default=None, help="model name (default: the server's first)")
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    results = {}
    for name, client in (("rest", RestClient(args.rest)), ("grpc", GrpcClient(args.grpc, stream=True))):
        with client:
            results[name] = drive(client, args.model, args.steps, args.seed)
        print(
            f"{name}: {args.steps} actions of shape {results[name].shape[1:]}, goal switched at {args.steps // 2}"
        )
    same = np.array_equal(results["rest"], results["grpc"])
    print("rest and grpc answered the same actions" if same else "rest and grpc answered different actions")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
