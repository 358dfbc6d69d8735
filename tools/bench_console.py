"""Does an open server console slow the act path? REST acts/s at 256 sessions with and without one console, same
server process, same run, rounds alternated (docs/ui.md).

Load: wrk, one thread, one connection per session, each request an act of the next session (as `gmt bench`'s
`rest` figure). The console, as the page holds it on a session's page and on the listing: one server-sent event
stream of one of the sessions under load, read as fast as it comes, and `GET /sessions?limit=50` once a second.

    .venv/bin/python tools/bench_console.py [--checkpoint checkpoints/halfcheetah-gmt] [--sessions 256]
        [--seconds 8] [--rounds 3]

Prints one JSON document: each round's figures and the medians.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import httpx

OBS = [0.01 * ((i * 7) % 11 - 5) for i in range(17)]

WRK_SCRIPT = """
local ids = {%s}
local body = '%s'
local i = 0
request = function()
  i = i + 1
  return wrk.format("POST", "/sessions/" .. ids[(i %% #ids) + 1] .. "/act", {["Content-Type"] = "application/json"}, body)
end
done = function(summary, latency, requests)
  local e = summary.errors
  io.write(string.format('WRK {"requests":%%d,"duration_us":%%d,"errors":%%d,"p50_us":%%d,"p99_us":%%d}\\n',
    summary.requests, summary.duration, e.connect + e.read + e.write + e.timeout + e.status,
    latency:percentile(50), latency:percentile(99)))
end
"""


def serve(checkpoint: Path) -> tuple[subprocess.Popen, str]:
    """`gmt serve` on free loopback ports: (process, REST URL)."""
    exe = Path(sys.executable).parent / "gmt"
    args = [str(exe), "serve", "-c", str(checkpoint), "--rest-port", "0", "--grpc-port", "0"]
    args += ["--max-sessions", "4096", "--log-level", "INFO"]
    env = {k: v for k, v in os.environ.items() if not k.startswith("GMT_")}
    proc = subprocess.Popen(args, stderr=subprocess.PIPE, text=True, env=env)
    for line in proc.stderr:
        rec = json.loads(line) if line.startswith("{") else {}
        if rec.get("msg") == "serving":
            threading.Thread(target=lambda: [None for _ in proc.stderr], daemon=True).start()
            return proc, f"http://127.0.0.1:{rec['rest_port']}"
    raise RuntimeError("gmt serve exited before serving")


def wrk(url: str, sids: list[str], seconds: int) -> dict:
    """Acts/s, p50 and p99 of one wrk run."""
    script = WRK_SCRIPT % (",".join(f'"{s}"' for s in sids), json.dumps({"observation": OBS}))
    with tempfile.NamedTemporaryFile("w", suffix=".lua", delete=False) as f:
        f.write(script)
    try:
        cmd = [
            "wrk",
            "-t",
            "1",
            "-c",
            str(len(sids)),
            "-d",
            f"{seconds}s",
            "--timeout",
            "10s",
            "-s",
            f.name,
            url,
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout
    finally:
        os.unlink(f.name)
    r = json.loads(next(line[4:] for line in out.splitlines() if line.startswith("WRK ")))
    return {
        "acts_per_s": round(r["requests"] / (r["duration_us"] / 1e6), 1),
        "p50_ms": r["p50_us"] / 1000,
        "p99_ms": r["p99_us"] / 1000,
        "errors": r["errors"],
    }


class Console:
    """What an open console asks of the server: one session's event stream and the listing once a second."""

    def __init__(self, url: str, sid: str) -> None:
        self.url, self.sid = url, sid
        self.stop = threading.Event()
        self.events: dict[str, int] = {}
        self.listings = 0
        self.opened = threading.Event()
        self.threads = [threading.Thread(target=f, daemon=True) for f in (self._stream, self._poll)]

    def __enter__(self) -> Console:
        for t in self.threads:
            t.start()
        if not self.opened.wait(30):
            raise RuntimeError("the event stream did not open")
        return self

    def __exit__(self, *exc) -> None:
        self.stop.set()
        for t in self.threads:
            t.join(30)

    def _stream(self) -> None:
        with httpx.stream(
            "GET", f"{self.url}/sessions/{self.sid}/events", timeout=httpx.Timeout(30, read=60)
        ) as r:
            r.raise_for_status()
            self.opened.set()
            for line in r.iter_lines():
                if line.startswith("event: "):
                    self.events[line[7:]] = self.events.get(line[7:], 0) + 1
                if self.stop.is_set():
                    return

    def _poll(self) -> None:
        with httpx.Client(base_url=self.url, timeout=30) as c:
            while not self.stop.wait(1.0):
                c.get("/sessions", params={"limit": 50}).raise_for_status()
                self.listings += 1


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--checkpoint", type=Path, default=Path("checkpoints/halfcheetah-gmt"))
    p.add_argument("--sessions", type=int, default=256)
    p.add_argument("--seconds", type=int, default=8)
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args()
    proc, url = serve(a.checkpoint)
    try:
        with httpx.Client(base_url=url, timeout=30) as c:
            model = c.get("/models").json()["models"][0]["name"]
            sids = [
                c.post("/sessions", json={"model": model, "goal": i % 3, "seed": i}).json()["session_id"]
                for i in range(a.sessions)
            ]
        wrk(url, sids, 2)  # warm-up
        rounds = []
        for _ in range(a.rounds):
            without = wrk(url, sids, a.seconds)
            with Console(url, sids[0]) as console:
                with_console = wrk(url, sids, a.seconds)
            rounds.append(
                {
                    "without_console": without,
                    "with_console": with_console,
                    "console_events": console.events,
                    "console_listings": console.listings,
                }
            )
            print(
                f"[bench] {without['acts_per_s']}/s without, {with_console['acts_per_s']}/s with",
                file=sys.stderr,
            )
        med = {
            k: statistics.median(r[k]["acts_per_s"] for r in rounds)
            for k in ("without_console", "with_console")
        }
        print(
            json.dumps(
                {
                    "checkpoint": str(a.checkpoint),
                    "sessions": a.sessions,
                    "seconds_per_run": a.seconds,
                    "cores": os.cpu_count(),
                    "rounds": rounds,
                    "median_acts_per_s": med,
                    "with_vs_without": round(med["with_console"] / med["without_console"], 3),
                },
                indent=2,
            )
        )
    finally:
        proc.terminate()
        proc.wait(30)


if __name__ == "__main__":
    main()
