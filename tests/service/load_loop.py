"""A bounded load loop in its own process: `python load_loop.py URL MODEL SESSIONS STOP_FILE MAX_S`.

Creates SESSIONS sessions, then acts on all of them concurrently (each session's acts in order, with their step)
until STOP_FILE exists or MAX_S seconds have passed, closes them, and prints one JSON line: acts, errors (by status
and code), the versions the sessions ran, seconds. Prints `ready` once every session has acted once.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections import Counter
from pathlib import Path

import httpx


async def main(url: str, model: str, n: int, stop: Path, max_s: float) -> dict:
    errors: Counter[str] = Counter()
    acts = 0
    limits = httpx.Limits(max_connections=64)
    async with httpx.AsyncClient(base_url=url, timeout=60, limits=limits) as http:
        sessions = []
        for i in range(n):
            r = await http.post("/sessions", json={"model": model, "goal": i % 3, "seed": i})
            r.raise_for_status()
            sessions.append(r.json())
        obs = [0.01 * (i % 17) for i in range(17)]
        t0 = time.monotonic()
        started = 0

        async def episode(s: dict) -> None:
            nonlocal acts, started
            step = 0
            while not stop.exists() and time.monotonic() - t0 < max_s:
                try:
                    r = await http.post(
                        f"/sessions/{s['session_id']}/act", json={"observation": obs, "step": step}
                    )
                except httpx.HTTPError as e:
                    errors[type(e).__name__] += 1
                    continue
                if r.status_code != 200:
                    errors[f"{r.status_code} {r.json().get('error', {}).get('code')}"] += 1
                    continue
                step += 1
                acts += 1
                if step == 1:
                    started += 1
                    if started == n:
                        print("ready", flush=True)

        await asyncio.gather(*(episode(s) for s in sessions))
        seconds = time.monotonic() - t0
        for s in sessions:
            r = await http.delete(f"/sessions/{s['session_id']}")
            if r.status_code != 204:
                errors[f"close {r.status_code}"] += 1
    versions = sorted({s["model_version"] for s in sessions})
    return {"acts": acts, "errors": dict(errors), "versions": versions, "seconds": round(seconds, 2)}


if __name__ == "__main__":
    url, model, n, stop, max_s = (
        sys.argv[1],
        sys.argv[2],
        int(sys.argv[3]),
        Path(sys.argv[4]),
        float(sys.argv[5]),
    )
    print(json.dumps(asyncio.run(main(url, model, n, stop, max_s))), flush=True)
