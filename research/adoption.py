"""What adopting sessions costs: N sessions acted STEPS times on server A, then `POST /act` of all of them on server
B (both on one private Redis), then back on A; each call's time. With PROFILE=1, py-spy records B into
/tmp/adopt.txt (raw) while it adopts (py-spy slows what it samples).

Run from the repository root: `python -m research.adoption [N] [STEPS]` (docs/performance.md).
"""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import httpx

from gmt.bench import harness as h

n = int(sys.argv[1]) if len(sys.argv) > 1 else 256
steps = int(sys.argv[2]) if len(sys.argv) > 2 else 25
ckpt = Path("checkpoints/halfcheetah-gmt")
redis, url = h.redis_server()
procs = []
try:
    a, ia = h.start_server(ckpt, naive=False, extra=("--redis-url", url))
    procs.append(a)
    b, ib = h.start_server(ckpt, naive=False, extra=("--redis-url", url))
    procs.append(b)
    ua, ub = (f"http://127.0.0.1:{i['rest_port']}" for i in (ia, ib))
    sids = h.open_sessions(ua, ia["models"][0], n)
    obs = json.loads(h.obs_json())
    body = {"requests": [{"session_id": s, "observation": obs} for s in sids]}
    spy = None
    with httpx.Client(timeout=60) as c:
        for _ in range(steps):  # the history each session carries to B
            assert c.post(f"{ua}/act", json=body).status_code == 200
        if os.environ.get("PROFILE") == "1":
            args = ["py-spy", "record", "-p", str(b.pid), "-r", "500", "-f", "raw", "-o", "/tmp/adopt.txt"]
            spy = subprocess.Popen([*args, "-d", "4"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            time.sleep(1.0)  # py-spy attaches (a profile only: the timings below are not taken with it)
        calls = [
            ("B first", ub),
            ("B second", ub),
            ("B third", ub),
            ("A again, first", ua),
            ("A again, second", ua),
        ]
        for who, u in calls:
            t = time.perf_counter()
            r = c.post(f"{u}/act", json=body)
            ms = (time.perf_counter() - t) * 1000
            errors = sum(1 for x in r.json()["results"] if "error" in x)
            print(f"{who}: {ms:.1f} ms for {n} sessions ({ms / n * 1000:.0f} us each), item errors {errors}")
    if spy is not None:
        spy.wait()
finally:
    for p in procs:
        p.terminate()
        p.wait(30)
    redis.terminate()
