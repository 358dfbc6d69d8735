"""`gmt run --live`: a local page that shows the episode as it runs and changes its goal on a click.

The page (`clients/static/live.*`) reads one server-sent event stream, `GET /events`: the model's goal table first,
then per update the steps since the last one (step, goal, running statistic) and the newest rendered frame as a
JPEG (Pillow, which the `run` extra brings) or PNG (standard library) data URL. A goal button posts `POST /goal`;
the run loop applies it through the policy server (REST or gRPC, the run's own session) before its next act, and
the answer says from which step it holds.

Standard library only (`http.server` in a thread): the client needs nothing beyond its base install. Frames are
rendered only while a page watches, at most `fps` a second, and each viewer gets the newest one, so a slow page
never slows the episode nor queues frames. The server listens on 127.0.0.1 by default; goal changes must come as
JSON from a page of this server (`Host` and `Origin` checked), so another site open in the browser cannot post them.
"""

from __future__ import annotations

import base64
import json
import queue
import struct
import threading
import time
import zlib
from collections import deque
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import numpy as np

from gmt.client.base import ModelInfo, Session

STATIC = Path(__file__).parent / "static"
ASSETS = {
    "/": ("live.html", "text/html; charset=utf-8"),
    "/live.js": ("live.js", "text/javascript; charset=utf-8"),
    "/live.css": ("live.css", "text/css; charset=utf-8"),
}
CSP = (
    "default-src 'none'; script-src 'self'; style-src 'self'; connect-src 'self'; img-src 'self' data:; "
    "base-uri 'none'; form-action 'none'; frame-ancestors 'none'"
)
POINTS = 2000  # steps of the running statistic kept for a page that connects late
GOAL_WAIT_S = 30.0  # longest a goal click waits for the run loop to apply it
UPDATE_EVERY_S = 0.05  # a page gets at most 20 updates a second


def encode_frame(frame: np.ndarray) -> str:
    """An HxWx3 (or HxW) uint8 frame as a data URL: JPEG through Pillow when installed, else PNG."""
    rgb = np.asarray(frame, dtype=np.uint8)
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    try:
        import io

        from PIL import Image
    except ImportError:
        return "data:image/png;base64," + base64.b64encode(png(rgb)).decode()
    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(rgb[:, :, :3])).save(buf, format="JPEG", quality=80)
    return "data:image/jpeg;base64," + base64.b64encode(buf.getvalue()).decode()


def png(rgb: np.ndarray) -> bytes:
    """An HxWx3 uint8 image as PNG bytes (standard library only)."""
    h, w, _ = rgb.shape
    rows = np.concatenate([np.zeros((h, 1), np.uint8), np.ascontiguousarray(rgb).reshape(h, w * 3)], axis=1)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)  # 8-bit RGB
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(rows.tobytes(), 3))
        + chunk(b"IEND", b"")
    )


@dataclass
class GoalRequest:
    """A goal change asked for by the page, answered by the run loop."""

    goal: int
    done: threading.Event = field(default_factory=threading.Event)
    answer: dict | None = None
    error: str | None = None


class LiveView:
    """The live page's server and the state it shows.

    The run loop calls `episode` at each episode's start, `apply_goals` before each act, and `step` after each
    environment step; the page's threads read what they store.

    Args:
        spec: The served model (its goal table draws the goal bands and the buttons).
        env_id: The environment stepped.
        transport: How the policy server is reached (shown on the page).
        host: Address to listen on.
        port: Port to listen on (0: any free port; `url` tells which).
        fps: Frames per second at most.
    """

    def __init__(
        self,
        spec: ModelInfo,
        env_id: str,
        transport: str,
        host: str = "127.0.0.1",
        port: int = 8765,
        fps: float = 20,
    ) -> None:
        self.spec, self.env_id, self.transport = spec, env_id, transport
        self.frame_interval_s = 1.0 / fps
        self._cond = threading.Condition()
        self._seq = 0  # bumped by every change a page should see
        self._episode = -1
        self._session_id = ""
        self._points: deque[tuple[int, int, int, float]] = deque(
            maxlen=POINTS
        )  # (index, step, goal, statistic)
        self._index = 0
        self._frame: tuple[int, np.ndarray, int, int] | None = None  # (frame number, pixels, step, goal)
        self._frame_url: tuple[int, str] | None = None  # the newest frame encoded, by frame number
        self._frames = 0
        self._last_frame_t = -float("inf")
        self._viewers = 0
        self._finished = False
        self._closed = threading.Event()
        self._goals: queue.SimpleQueue[GoalRequest] = queue.SimpleQueue()
        self._server = ThreadingHTTPServer((host, port), _handler(self))
        self._server.daemon_threads = True
        self.host, self.port = self._server.server_address[:2]
        self._thread = threading.Thread(target=self._server.serve_forever, name="gmt-live", daemon=True)
        self._thread.start()

    @property
    def url(self) -> str:
        """The page's address."""
        host = f"[{self.host}]" if ":" in str(self.host) else self.host
        return f"http://{host}:{self.port}/"

    # ----- the run loop's side -------------------------------------------------------------------------------------
    def episode(self, episode: int, session_id: str) -> None:
        """A new episode starts in session `session_id`."""
        with self._cond:
            self._episode, self._session_id = episode, session_id
            self._points.clear()
            self._frame = self._frame_url = None
            self._seq += 1
            self._cond.notify_all()

    def wants_frame(self) -> bool:
        """Whether the run loop should render a frame for `step` now (a page watches, and one is due)."""
        return self._viewers > 0 and time.monotonic() - self._last_frame_t >= self.frame_interval_s

    def step(self, step: int, goal: int, statistic: float, frame: np.ndarray | None = None) -> None:
        """Record one environment step: the goal the server answered with, the running statistic, a frame."""
        with self._cond:
            self._index += 1
            self._points.append((self._index, step, goal, statistic))
            if frame is not None:
                self._frames += 1
                self._frame = (self._frames, frame, step, goal)
                self._last_frame_t = time.monotonic()
            self._seq += 1
            self._cond.notify_all()

    def apply_goals(self, session: Session) -> None:
        """Apply the goal changes the page asked for, in order, to `session` (through the policy server)."""
        while True:
            try:
                req = self._goals.get_nowait()
            except queue.Empty:
                return
            try:
                info = session.set_goal(req.goal)
                req.answer = {"goal": info.goal, "goal_name": info.goal_name, "step": info.step}
            except Exception as e:  # noqa: BLE001 - the page shows it; the run goes on
                req.error = str(e)
            req.done.set()

    def wait_for_viewer(self) -> None:
        """Block until a page watches (Ctrl-C interrupts)."""
        with self._cond:
            while not self._cond.wait_for(lambda: self._viewers > 0, timeout=0.5):
                pass

    def finish(self) -> None:
        """Tell the pages the run ended and refuse goal requests left; the page stays served (idempotent)."""
        with self._cond:
            if self._finished:
                return
            self._finished = True
            self._seq += 1
            self._cond.notify_all()
        while True:
            try:
                req = self._goals.get_nowait()
            except queue.Empty:
                break
            req.error = "the run has ended"
            req.done.set()

    def hold(self) -> None:
        """Keep serving the finished run's page until Ctrl-C (KeyboardInterrupt) or `close`."""
        while not self._closed.wait(0.5):
            pass

    def close(self) -> None:
        """Tell the pages the run ended, refuse goal requests left, stop serving (idempotent)."""
        self.finish()
        if self._closed.is_set():
            return
        self._closed.set()
        self._server.shutdown()
        self._server.server_close()

    # ----- the pages' side ---------------------------------------------------------------------------------------
    def ask_goal(self, goal: int | str) -> GoalRequest:
        """Queue a goal change for the run loop. Raises KeyError for a goal the model does not have."""
        req = GoalRequest(self.spec.goal(goal).id)
        if self._finished:
            req.error = "the run has ended"
            req.done.set()
        else:
            self._goals.put(req)
        return req

    def intro(self) -> dict:
        """What a page needs first: the model, its goal table, the transport."""
        return {
            "model": self.spec.name,
            "env_id": self.env_id,
            "statistic": self.spec.statistic,
            "transport": self.transport,
            "goals": [{"id": g.id, "name": g.name, "mean": g.mean, "std": g.std} for g in self.spec.goals],
        }

    def stream(self, write, stop: threading.Event) -> None:
        """Write the page's event stream with `write(bytes)` until the run ends, `stop` is set or a write fails."""
        with self._cond:
            self._viewers += 1
            self._cond.notify_all()  # `wait_for_viewer`
        try:
            write(_event("intro", self.intro()))
            seen, index, episode, frame_no = -1, 0, None, 0
            while not stop.is_set():
                with self._cond:
                    self._cond.wait_for(lambda s=seen: self._seq != s or stop.is_set(), timeout=15.0)
                    if self._seq == seen:
                        snapshot = None
                    else:
                        seen = self._seq
                        points = [p for p in self._points if p[0] > index]
                        snapshot = (self._episode, self._session_id, points, self._frame, self._finished)
                if snapshot is None:
                    write(b": keep-alive\n\n")
                    continue
                ep, sid, points, frame, finished = snapshot
                if ep != episode:
                    episode = ep
                    write(_event("episode", {"episode": ep, "session_id": sid}))
                data: dict = {"points": [[s, g, None if v != v else v] for _, s, g, v in points]}
                if points:
                    index = points[-1][0]
                if frame is not None and frame[0] != frame_no:
                    frame_no = frame[0]
                    data["frame"] = {"url": self._encoded(frame), "step": frame[2], "goal": frame[3]}
                if data["points"] or "frame" in data:
                    write(_event("update", data))
                if finished:
                    write(_event("end", {}))
                    return
                stop.wait(UPDATE_EVERY_S)  # what comes meanwhile goes in the next update
        finally:
            with self._cond:
                self._viewers -= 1

    def _encoded(self, frame: tuple[int, np.ndarray, int, int]) -> str:
        cached = self._frame_url
        if cached is not None and cached[0] == frame[0]:
            return cached[1]
        url = encode_frame(frame[1])  # outside the lock: the run loop never waits for an encoding
        self._frame_url = (frame[0], url)
        return url


def _event(kind: str, data: dict) -> bytes:
    return f"event: {kind}\ndata: {json.dumps(data, separators=(',', ':'))}\n\n".encode()


def _handler(view: LiveView) -> type[BaseHTTPRequestHandler]:
    class Handler(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"
        server_version = "gmt-live"

        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the base class's name
            pass  # the run's own output stays readable

        def _send(self, status: int, body: bytes, content_type: str = "application/json") -> None:
            self.send_response(status)
            if status >= 400:  # a body left unread must not be taken for the next request
                self.send_header("Connection", "close")
                self.close_connection = True
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Content-Security-Policy", CSP)
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def _error(self, status: int, message: str) -> None:
            self._send(status, json.dumps({"error": {"message": message}}).encode())

        def _same_origin(self) -> bool:
            """The Host is this server's (no DNS rebinding; any host when listening on every address), and a
            request from a page sends this server's Origin."""
            port = view.port
            hosts = {f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}", f"{view.host}:{port}"}
            host = self.headers.get("Host", "")
            origin = self.headers.get("Origin")
            known = host in hosts or view.host in ("0.0.0.0", "::")
            return known and (origin is None or origin == f"http://{host}")

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            path = self.path.split("?", 1)[0]
            if not self._same_origin():
                return self._error(403, "this page is served for this host only")
            if path in ASSETS:
                name, content_type = ASSETS[path]
                return self._send(200, (STATIC / name).read_bytes(), content_type)
            if path != "/events":
                return self._error(404, f"no page {path}; the live view is at /")
            self.send_response(200)
            self.send_header("Content-Type", "text/event-stream; charset=utf-8")
            self.send_header("Cache-Control", "no-store")
            self.send_header("Connection", "close")
            self.end_headers()
            self.close_connection = True
            stop = threading.Event()

            def write(chunk: bytes) -> None:
                self.wfile.write(chunk)
                self.wfile.flush()

            try:
                view.stream(write, stop)
            except OSError:
                pass  # the page went away

        def do_POST(self) -> None:  # noqa: N802 - http.server's name
            if self.path != "/goal":
                return self._error(404, f"no endpoint POST {self.path}")
            if not self._same_origin():
                return self._error(403, "goal changes are taken from this server's own page only")
            if self.headers.get("Content-Type", "").split(";")[0].strip() != "application/json":
                return self._error(415, 'send the goal as JSON: {"goal": <id or name>}')
            try:
                size = int(self.headers.get("Content-Length", "0"))
                if not 0 < size <= 4096:
                    raise ValueError
                goal = json.loads(self.rfile.read(size))["goal"]
                if isinstance(goal, bool) or not isinstance(goal, int | str):
                    raise ValueError
            except (ValueError, KeyError, TypeError):
                return self._error(400, 'the body must be {"goal": <id or name>} (at most 4096 bytes)')
            try:
                req = view.ask_goal(goal)
            except KeyError as e:
                return self._error(400, e.args[0])
            if not req.done.wait(GOAL_WAIT_S):
                return self._error(504, f"the run did not apply the goal within {GOAL_WAIT_S:g} s")
            if req.error is not None:
                return self._error(409, req.error)
            self._send(200, json.dumps(req.answer).encode())

    return Handler
