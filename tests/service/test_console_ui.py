"""The server console (`/ui`) in a real headless Chromium against a real server with auth on: the token form, the
listing following a session the test drives, the session page's goal buttons, target slider and close button
(checked over REST), and no request leaving loopback."""

from __future__ import annotations

import time

import httpx
import pytest
from browser_support import external, requested_urls, save_screenshot
from service_harness import OBS_DIM, RunningServer, make_settings

pytest.importorskip("selenium")
from selenium.common.exceptions import StaleElementReferenceException  # noqa: E402
from selenium.webdriver.common.by import By  # noqa: E402
from selenium.webdriver.support.ui import WebDriverWait  # noqa: E402

TOKEN = "ui-token"
TIMEOUT_S = 60  # generous: a busy 2-core machine runs the server, the test and Chromium


@pytest.fixture
def served(ckpt_root):
    s = RunningServer(
        make_settings(checkpoints=[ckpt_root], auth_token=TOKEN, replica_id="ui-replica")
    ).start()
    with httpx.Client(base_url=s.url, timeout=30, headers={"Authorization": f"Bearer {TOKEN}"}) as api:
        yield s, api
    s.stop()


def _wait(driver, condition, message: str):
    # The listing is redrawn every second: an element found just before a redraw goes stale; look again.
    wait = WebDriverWait(
        driver, TIMEOUT_S, poll_frequency=0.1, ignored_exceptions=(StaleElementReferenceException,)
    )
    return wait.until(condition, message)


def _shown(element_id: str):
    """A wait condition: the element, once displayed."""

    def shown(driver):
        el = driver.find_element(By.ID, element_id)
        return el if el.is_displayed() else None

    return shown


def _text(driver, css: str) -> str:
    for _ in range(20):  # the listing is redrawn every second: read again if the element went stale meanwhile
        try:
            els = driver.find_elements(By.CSS_SELECTOR, css)
            return els[0].text if els else ""
        except StaleElementReferenceException:
            continue
    raise AssertionError(f"{css} kept going stale")


def _act(api: httpx.Client, sid: str, n: int) -> None:
    for _ in range(n):
        r = api.post(f"/sessions/{sid}/act", json={"observation": [0.2] * OBS_DIM})
        assert r.status_code == 200, r.text


def _goal(api: httpx.Client, sid: str) -> str:
    return api.get(f"/sessions/{sid}").json()["goal_name"]


def _sign_in(driver, server, token: str = TOKEN) -> None:
    """Open /ui; auth is on, so the page asks for the token, keeps it in sessionStorage and sends it on every call."""
    driver.get(f"{server.url}/ui")
    form = _wait(driver, _shown("token-form"), "no token form")
    driver.find_element(By.ID, "token").send_keys(token)
    form.submit()


def test_console_follows_a_session_and_steers_it(chromium, served, tmp_path):
    server, api = served
    sid = api.post("/sessions", json={"model": "tiny-gmt", "goal": "low"}).json()["session_id"]
    other = api.post("/sessions", json={"model": "tiny-cartpole", "goal": 0}).json()["session_id"]
    _act(api, sid, 3)
    d = chromium
    _sign_in(d, server)
    row = f'#sessions tr[data-session="{sid}"]'
    _wait(d, lambda d: _text(d, f"{row} td.step") == "3", "the session is not listed at step 3")
    assert _text(d, f'#sessions tr[data-session="{other}"] td.step') == "0"
    assert "tiny-gmt" in _text(d, row) and "ui-replica" in _text(d, row) and "low" in _text(d, row)
    assert _text(d, '.model[data-model="tiny-gmt"]').count("low") == 1  # the goal table

    _act(api, sid, 5)  # the listing updates without a reload
    _wait(d, lambda d: _text(d, f"{row} td.step") == "8", "the listed step did not advance to 8")
    save_screenshot(d, "ui-console.png", tmp_path)

    _wait(d, lambda d: d.find_element(By.CSS_SELECTOR, f"{row} a").click() or True, "the row's link")
    _wait(d, lambda d: d.find_element(By.ID, "s-id").text == sid, "the session page did not open")
    high = _wait(
        d, lambda d: d.find_element(By.CSS_SELECTOR, '#goal-buttons button[data-goal="high"]'), "no buttons"
    )
    _act(api, sid, 20)  # the page follows the event stream
    _wait(d, lambda d: d.find_element(By.ID, "s-step").text == "28", "the event stream did not bring step 28")

    high.click()
    deadline = time.monotonic() + TIMEOUT_S
    while _goal(api, sid) != "high":  # the click went through the public API
        assert time.monotonic() < deadline, "clicking 'high' did not change the session's goal"
        time.sleep(0.05)
    _wait(d, lambda d: d.find_element(By.ID, "s-goal").get_attribute("data-goal") == "2", "goal not shown")
    _act(api, sid, 30)
    _wait(d, lambda d: d.find_element(By.ID, "s-step").text == "58", "no act after the goal change")
    save_screenshot(d, "ui-session.png", tmp_path)

    # The target slider spans the goal means (0..2): 1.1 is nearest to medium's mean.
    d.execute_script(
        "const s = document.getElementById('target'); s.value = 1.1; s.dispatchEvent(new Event('input'))"
    )
    d.find_element(By.ID, "set-target").click()
    deadline = time.monotonic() + TIMEOUT_S
    while _goal(api, sid) != "medium":
        assert time.monotonic() < deadline, "the target slider did not change the goal"
        time.sleep(0.05)

    d.find_element(By.ID, "close").click()
    _wait(d, lambda d: "closed" in d.find_element(By.ID, "s-state").text, "the close is not shown")
    assert api.get(f"/sessions/{sid}").status_code == 404

    urls = requested_urls(d)
    assert any(u.endswith("/ui/console.js") for u in urls) and any(
        f"/sessions/{sid}/events" in u for u in urls
    )
    assert external(urls) == [], "the console requested something off loopback"
    api.delete(f"/sessions/{other}")


def test_a_wrong_token_is_refused_and_the_form_stays(chromium, served):
    server, _ = served
    d = chromium
    d.get(f"{server.url}/ui")
    d.execute_script("sessionStorage.clear()")
    d.refresh()
    form = _wait(d, _shown("token-form"), "no token form")
    d.find_element(By.ID, "token").send_keys("not-the-token")
    form.submit()
    _wait(d, lambda d: "invalid bearer token" in d.find_element(By.ID, "message").text, "no message")
    assert d.find_element(By.ID, "token-form").is_displayed()
    assert d.find_elements(By.CSS_SELECTOR, "#sessions tbody tr") == []


def test_the_listing_updates_rows_in_place_and_a_gone_session_shows_no_controls(chromium, served):
    """A link the operator has focused (or is clicking) survives the every-second poll (rows were rebuilt, which
    dropped focus and half-made clicks); a session page never shows another session's goal buttons."""
    server, api = served
    sid = api.post("/sessions", json={"model": "tiny-gmt", "goal": "low"}).json()["session_id"]
    d = chromium
    _sign_in(d, server)
    row = f'#sessions tr[data-session="{sid}"]'
    _wait(d, lambda d: _text(d, f"{row} td.step") == "0", "the session is not listed")
    link = d.find_element(By.CSS_SELECTOR, f"{row} a")
    d.execute_script("arguments[0].focus()", link)
    _act(api, sid, 4)
    _wait(d, lambda d: _text(d, f"{row} td.step") == "4", "the listed step did not advance")
    assert link.is_displayed()  # the same element: a rebuilt row raises StaleElementReferenceException
    assert d.switch_to.active_element == link

    d.get(f"{server.url}/ui#/session/{sid}")  # a session's page, then one that does not exist
    _wait(d, lambda d: d.find_elements(By.CSS_SELECTOR, "#goal-buttons button"), "no goal buttons")
    d.execute_script("location.hash = '#/session/nope'")
    _wait(
        d, lambda d: "not_found" in d.find_element(By.ID, "message").text, "the missing session is not said"
    )
    assert d.find_element(By.ID, "s-id").text == "nope"
    assert not d.find_element(By.ID, "controls").is_displayed()
    assert d.find_elements(By.CSS_SELECTOR, "#goal-buttons button") == []
    api.delete(f"/sessions/{sid}")


def test_with_keys_the_console_shows_only_the_keys_sessions(chromium, ckpt_root, tmp_path):
    """Signed in with one key of `--auth-tokens`, the listing holds that key's sessions only, and another key's
    session page says not_found (its detail and event stream answer 404)."""
    keys = tmp_path / "keys.txt"
    keys.write_text("alice:alice-ui-token\nbob:bob-ui-token\n")
    server = RunningServer(make_settings(checkpoints=[ckpt_root], auth_tokens=keys)).start()
    try:
        with httpx.Client(base_url=server.url, timeout=30) as api:
            body = {"model": "tiny-gmt", "goal": "low"}
            mine = api.post("/sessions", json=body, headers={"Authorization": "Bearer alice-ui-token"})
            theirs = api.post("/sessions", json=body, headers={"Authorization": "Bearer bob-ui-token"})
            mine, theirs = mine.json()["session_id"], theirs.json()["session_id"]
        d = chromium
        d.get(f"{server.url}/ui")
        d.execute_script("sessionStorage.clear()")
        _sign_in(d, server, "alice-ui-token")
        _wait(
            d,
            lambda d: _text(d, f'#sessions tr[data-session="{mine}"] td.step') == "0",
            "own session not listed",
        )
        listed = [
            r.get_attribute("data-session") for r in d.find_elements(By.CSS_SELECTOR, "#sessions tbody tr")
        ]
        assert listed == [mine]
        d.execute_script(f"location.hash = '#/session/{theirs}'")
        _wait(
            d,
            lambda d: "not_found" in d.find_element(By.ID, "message").text,
            "another key's session is shown",
        )
        assert not d.find_element(By.ID, "controls").is_displayed()
    finally:
        server.stop()
