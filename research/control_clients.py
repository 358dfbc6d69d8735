"""One session's act p50 from a separate client process, by client: a bare grpc.aio Control stream (the bench's),
`gmt.client`'s sync `ControlStream`, and `GrpcClient.act` (unary); one in-memory server, rounds alternated.

Run from the repository root: `python -m research.control_clients [ROUNDS]` (docs/performance.md).
"""

import json
import statistics
import subprocess
import sys
from pathlib import Path

from gmt.bench import harness as h

ROUNDS = int(sys.argv[1]) if len(sys.argv) > 1 else 3
SECS = 5
SYNC = r"""
import json, sys, time, numpy as np
from gmt.client.grpc import GrpcClient
from gmt.bench.harness import obs_json
t, sid, secs, stream = sys.argv[1], sys.argv[2], float(sys.argv[3]), sys.argv[4] == "1"
from gmt.client.grpc import ControlStream, act_request
from gmt.v1 import policy_pb2 as pb
c = GrpcClient(t, stream=stream)
obs = json.loads(obs_json()); lat = []
if stream:
    cs = ControlStream(c, sid)
    class _A:
        def act(self, sid, obs):
            return cs.call(pb.ControlRequest(act=act_request(sid, obs, None, None)))
    c = _A()
stop = time.perf_counter() + secs
while time.perf_counter() < stop:
    t0 = time.perf_counter(); c.act(sid, obs); lat.append(time.perf_counter() - t0)
ms = np.asarray(lat[len(lat)//10:]) * 1000
print(json.dumps({"p50_ms": round(float(np.percentile(ms, 50)), 3), "p99_ms": round(float(np.percentile(ms, 99)), 3), "acts_per_s": round(len(lat)/secs, 1)}))
"""
proc, info = h.start_server(Path("checkpoints/halfcheetah-gmt"), naive=False)
try:
    url = f"http://127.0.0.1:{info['rest_port']}"
    target = f"127.0.0.1:{info['grpc_port']}"
    sids = h.open_sessions(url, info["models"][0], 1)
    res = {"aio stream": [], "sync ControlStream": [], "sync unary": []}
    for r in range(ROUNDS):
        res["aio stream"].append(h.grpc_load(target, sids, SECS, "stream")["p50_ms"])
        for name, flag in (("sync ControlStream", "1"), ("sync unary", "0")):
            out = subprocess.run(
                [sys.executable, "-c", SYNC, target, sids[0], str(SECS), flag],
                capture_output=True,
                text=True,
                check=True,
            ).stdout
            res[name].append(json.loads(out.strip().splitlines()[-1])["p50_ms"])
        print(r, {k: v[-1] for k, v in res.items()}, flush=True)
    print({k: statistics.median(v) for k, v in res.items()})
finally:
    proc.terminate()
    proc.wait(30)
