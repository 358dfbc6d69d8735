"""`gmt bench --sections console`: does an open server console slow the act path? REST acts/s with and without one
console, same server process, same run, rounds alternated (docs/ui.md).

The console, as the page holds it: one session's server-sent event stream (a session under load), read as fast as
it comes, and `GET /sessions?limit=50` once a second.
"""

from __future__ import annotations

import statistics
import sys
import threading
from pathlib import Path

import httpx

from gmt.bench.harness import bench_rest, close_sessions, open_sessions, start_server


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


def bench_console(checkpoint: Path, sessions: int = 256, seconds: float = 8.0, rounds: int = 3) -> dict:
    """`rounds` pairs of REST loads (wrk, one connection per session), without and with an open console."""
    proc, info = start_server(checkpoint, naive=False)
    url = f"http://127.0.0.1:{info['rest_port']}"
    try:
        sids = open_sessions(url, info["models"][0], sessions)
        bench_rest(url, sids, 2)  # warm-up
        out = []
        for _ in range(rounds):
            without = bench_rest(url, sids, seconds)
            with Console(url, sids[0]) as console:
                with_console = bench_rest(url, sids, seconds)
            out.append(
                {
                    "without_console": without,
                    "with_console": with_console,
                    "console_events": console.events,
                    "console_listings": console.listings,
                }
            )
            print(
                f"[bench] console: {without['acts_per_s']}/s without, {with_console['acts_per_s']}/s with",
                file=sys.stderr,
            )
        close_sessions(url, sids)
    finally:
        proc.terminate()
        proc.wait(30)
    med = {k: statistics.median(r[k]["acts_per_s"] for r in out) for k in ("without_console", "with_console")}
    return {
        "sessions": sessions,
        "seconds_per_run": seconds,
        "rounds": out,
        "median_acts_per_s": med,
        "with_vs_without": round(med["with_console"] / med["without_console"], 3),
    }
