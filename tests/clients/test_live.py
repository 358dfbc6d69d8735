"""`gmt run --live`: the page in a real headless Chromium while `gmt run` drives HalfCheetah-v5 over REST and over
the gRPC stream (frames that change, a goal click that changes the running session's goal, checked on the server,
nothing requested off loopback), and the live server's own rules without a browser."""

from __future__ import annotations

import io
import json
import queue
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest
from browser_support import external, requested_urls, save_screenshot
from service_harness import exec_after

from gmt.client.base import GoalInfo, ModelInfo, SessionInfo
from gmt.client.live import LiveView, encode_frame, png

TIMEOUT_S = 90  # generous: the server, MuJoCo rendering, `gmt run` and Chromium share a busy 2-core machine
GMT = Path(sys.executable).parent / "gmt"


class LiveRun:
    """`gmt run --live --port 0` in a subprocess; its output is read in a thread."""

    def __init__(self, *args: str, steps: str = "1000000", started: bool = True) -> None:
        cmd = [str(GMT), "run", "--live", "--port", "0", "--steps", steps, "--goal", "low", *args]
        # As in a terminal: a test run started in the background (`cmd &`) inherits an ignored SIGINT, and a Python
        # started with SIGINT ignored never raises KeyboardInterrupt, so Ctrl-C below would do nothing.
        cmd = exec_after("import signal; signal.signal(signal.SIGINT, signal.SIG_DFL)", cmd)
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        self.lines: queue.Queue[str] = queue.Queue()
        self.output: list[str] = []
        threading.Thread(target=self._read, daemon=True).start()
        if started:
            self.url = self.expect(r"live view at (\S+)")
            self.session_id = self.expect(r"episode 1/1: session (\w+)")

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.output.append(line)
            self.lines.put(line)

    def expect(self, pattern: str) -> str:
        """The first group of the next output line matching `pattern` (bounded wait)."""
        deadline = time.monotonic() + TIMEOUT_S
        while time.monotonic() < deadline and self.proc.poll() is None:
            try:
                m = re.search(pattern, self.lines.get(timeout=1))
            except queue.Empty:
                continue
            if m:
                return m.group(1)
        raise AssertionError(f"no line matching {pattern!r}; output: {''.join(self.output)[-2000:]}")

    def stop(self) -> int:
        """Interrupt the run as Ctrl-C does (the session is closed) and return its exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
        try:
            return self.proc.wait(30)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            return self.proc.wait(30)


@pytest.mark.parametrize("transport", ["rest", "grpc-stream"])
def test_live_page_shows_frames_and_a_goal_click_changes_the_session_goal(
    chromium, live_server, transport, tmp_path
):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    args = ["--server", live_server.rest_url]
    if transport == "grpc-stream":
        args = ["--grpc", live_server.grpc_target, "--stream"]
    run = LiveRun(*args)
    try:
        assert run.url.startswith("http://127.0.0.1:")
        d = chromium
        d.get(run.url)
        wait = WebDriverWait(d, TIMEOUT_S, poll_frequency=0.1)

        def frame() -> str:
            return d.find_element(By.ID, "frame").get_attribute("src") or ""

        first = wait.until(lambda d: frame() if frame().startswith("data:image/jpeg;base64,") else None)
        wait.until(lambda d: frame() != first, "the frame did not change")  # the episode moves on
        assert run.session_id in d.find_element(By.ID, "status").text
        assert "goal low" in d.find_element(By.ID, "caption").text

        d.find_element(By.CSS_SELECTOR, '#goals button[data-goal="2"]').click()
        message = wait.until(
            lambda d: re.search(r"goal high from step (\d+)", d.find_element(By.ID, "goal-message").text),
            "the click was not answered",
        )
        session = httpx.get(f"{live_server.rest_url}/sessions/{run.session_id}", timeout=30).json()
        assert session["goal_name"] == "high" and session["step"] >= int(message.group(1))
        # The frames rendered after the change say so, and the running segment's goal is the new one.
        wait.until(
            lambda d: "goal high" in d.find_element(By.ID, "caption").text, "frames do not show the goal"
        )
        wait.until(
            lambda d: "goal high" in d.find_element(By.ID, "status").text, "the steps do not show the goal"
        )
        if transport == "rest":
            save_screenshot(d, "ui-live.png", tmp_path)
        urls = requested_urls(d)
        assert any(u.endswith("/live.js") for u in urls) and any(u.endswith("/events") for u in urls)
        assert external(urls) == [], "the live page requested something off loopback"
    finally:
        status = run.stop()
    assert status == 130, "".join(run.output)[-2000:]  # interrupted, and the session closed on the way out
    assert httpx.get(f"{live_server.rest_url}/sessions/{run.session_id}", timeout=30).status_code == 404


SPEC = ModelInfo(
    "m",
    "HalfCheetah-v5",
    {},
    {},
    5,
    "mean_x_velocity",
    [GoalInfo(0, "low", 0.0, 0.1, -0.3, 0.3, 10), GoalInfo(1, "high", 2.0, 0.1, 1.7, 2.3, 10)],
)


class FakeSession:
    """Records the goals set through it."""

    def __init__(self) -> None:
        self.goals: list[int] = []

    def set_goal(self, goal):
        self.goals.append(goal)
        return SessionInfo("s", "m", goal, goal_name=SPEC.goal(goal).name, step=7)


@pytest.fixture
def view():
    v = LiveView(SPEC, "HalfCheetah-v5", "rest test", port=0)
    yield v
    v.close()


def test_goal_requests_are_checked_and_applied_by_the_run_loop(view):
    url = view.url
    with httpx.Client(timeout=30) as c:
        assert (
            c.post(url + "goal", content=b'{"goal": 1}').status_code == 415
        )  # not JSON: no simple form post
        assert (
            c.post(url + "goal", json={"goal": 1}, headers={"Origin": "http://other.example"}).status_code
            == 403
        )
        assert c.post(url + "goal", json={"goal": 1}, headers={"Host": "rebound.example"}).status_code == 403
        bad = c.post(url + "goal", json={"goal": "fast"})
        assert bad.status_code == 400 and "has no goal 'fast'" in bad.json()["error"]["message"]
        assert c.post(url + "goal", json={"target": 1}).status_code == 400
        assert c.post(url + "other", json={}).status_code == 404

        session = FakeSession()
        answers: list[httpx.Response] = []
        t = threading.Thread(target=lambda: answers.append(c.post(url + "goal", json={"goal": "high"})))
        t.start()
        deadline = time.monotonic() + 30
        while not session.goals:  # the run loop applies what the page asked for before its next act
            assert time.monotonic() < deadline, "the goal request never reached the run loop"
            view.apply_goals(session)
            time.sleep(0.01)
        t.join(30)
    assert session.goals == [1]
    assert answers[0].status_code == 200 and answers[0].json() == {"goal": 1, "goal_name": "high", "step": 7}


def test_frames_are_rendered_only_while_a_page_watches():
    view = LiveView(SPEC, "HalfCheetah-v5", "rest test", port=0, fps=0.001)  # a frame every 1000 s at most
    assert not view.wants_frame()
    got: queue.Queue[bytes] = queue.Queue()
    stop = threading.Event()
    t = threading.Thread(target=view.stream, args=(got.put, stop), daemon=True)
    t.start()
    assert got.get(timeout=30).startswith(b"event: intro")
    deadline = time.monotonic() + 30
    while not view.wants_frame():
        assert time.monotonic() < deadline
        time.sleep(0.01)
    view.episode(0, "sid")
    view.step(0, 1, 0.5, np.full((4, 6, 3), 200, np.uint8))
    chunks = b""
    while b'"frame"' not in chunks:
        chunks += got.get(timeout=30)
    update = json.loads(chunks.split(b"event: update\ndata: ")[1].split(b"\n\n")[0])
    assert update["points"] == [[0, 1, 0.5]] and update["frame"]["url"].startswith("data:image/")
    assert not view.wants_frame()  # the next one is due 1000 s later
    stop.set()
    view.close()
    t.join(30)
    assert not t.is_alive()


def test_frames_encode_as_jpeg_or_standard_library_png():
    from PIL import Image

    rgb = np.random.default_rng(0).integers(0, 256, (20, 30, 3), dtype=np.uint8)
    decoded = np.asarray(Image.open(io.BytesIO(png(rgb))))
    assert decoded.shape == (20, 30, 3) and np.array_equal(decoded, rgb)
    assert encode_frame(rgb[:, :, 0]).startswith("data:image/jpeg;base64,")  # grey frames too


def test_a_live_run_waits_for_a_page_and_keeps_it_after_the_end(live_server):
    """Unpaced, 30 steps end in well under a second: `--live` waits for a page before stepping, paces the episode at
    the environment's rate, and keeps serving the finished page until Ctrl-C."""
    run = LiveRun("--server", live_server.rest_url, steps="30", started=False)
    try:
        url = run.expect(r"waiting for a page to open (\S+)")
        assert not any(re.match(r"0 \(low\)", line) for line in run.output)  # not stepped: no segment yet
        with httpx.stream("GET", f"{url}events", timeout=TIMEOUT_S) as events:
            kinds = [line for line in events.iter_lines() if line.startswith("event: ")]
        assert kinds[0] == "event: intro" and kinds[-1] == "event: end"  # the stream ends with the run
        kept = run.expect(r"the run has ended; its page stays at (\S+) until Ctrl-C")
        assert kept == url and run.proc.poll() is None
        assert httpx.get(url, timeout=TIMEOUT_S).status_code == 200  # still served after the run
        assert any(re.match(r"0 \(low\)\s+0-29", line) for line in run.output), "".join(run.output)
    finally:
        status = run.stop()
    assert status == 130, "".join(run.output)[-2000:]
