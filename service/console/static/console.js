// The GMT server console: models, live sessions, and one session's live charts and controls.
// Plain JavaScript, no library, no build step. Every call goes to this server's public API with the bearer token
// (kept in this tab's sessionStorage) in an Authorization header; the event stream is read with fetch, since
// EventSource cannot send that header.
"use strict";

const TOKEN_KEY = "gmt-console-token";
const POLL_MS = 1000; // the sessions listing
const TIMEOUT_MS = 5000; // a call without an answer by then: the server is said not to respond
const PAGE = 50; // sessions per page
const HISTORY = 400; // steps the charts keep
const COLORS = ["#0969da", "#cf222e", "#1a7f37", "#9a6700", "#8250df", "#bf3989", "#0550ae", "#6e7781"];

const $ = (id) => document.getElementById(id);
const ui = { offset: 0, poll: null, view: null, models: new Map(), modelsShown: false, polling: false };

// ----- calls ----------------------------------------------------------------------------------------------------
function authHeaders(extra = {}) {
  const token = sessionStorage.getItem(TOKEN_KEY);
  return token ? { ...extra, Authorization: `Bearer ${token}` } : extra;
}

async function api(method, path, body) {
  const init = { method, headers: authHeaders(body === undefined ? {} : { "Content-Type": "application/json" }) };
  if (body !== undefined) init.body = JSON.stringify(body);
  init.signal = AbortSignal.timeout(TIMEOUT_MS);
  let r;
  try {
    r = await fetch(path, init);
  } catch (e) {
    if (e.name === "TimeoutError") throw new Error(`the server is not responding (no answer in ${TIMEOUT_MS / 1000} s)`);
    throw new Error(`the server cannot be reached (${e.message})`);
  }
  const text = await r.text();
  const doc = text ? JSON.parse(text) : null;
  if (r.status === 401) askToken();
  if (!r.ok) throw new Error(doc && doc.error ? `${doc.error.code}: ${doc.error.message}` : `HTTP ${r.status}`);
  return doc;
}

// Server-sent events over fetch: calls onEvent(kind, data) for each event until the stream ends or `signal` aborts.
async function readEvents(path, onEvent, signal) {
  const r = await fetch(path, { headers: authHeaders({ Accept: "text/event-stream" }), signal });
  if (r.status === 401) askToken();
  if (!r.ok) {
    const doc = await r.json().catch(() => null);
    throw new Error(doc && doc.error ? `${doc.error.code}: ${doc.error.message}` : `HTTP ${r.status}`);
  }
  const reader = r.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) return;
    buffer += decoder.decode(value, { stream: true });
    let end;
    while ((end = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, end);
      buffer = buffer.slice(end + 2);
      let kind = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith("event: ")) kind = line.slice(7);
        else if (line.startsWith("data: ")) data.push(line.slice(6));
      }
      if (data.length) onEvent(kind, JSON.parse(data.join("\n")));
    }
  }
}

function show(message) {
  $("message").textContent = message || "";
}

function askToken() {
  $("token-form").hidden = false;
  $("forget-token").hidden = true;
  $("token").focus();
}

$("token-form").addEventListener("submit", (e) => {
  e.preventDefault();
  sessionStorage.setItem(TOKEN_KEY, $("token").value);
  $("token").value = "";
  $("token-form").hidden = true;
  $("forget-token").hidden = false;
  show("");
  ui.models.clear();
  route();
});

$("forget-token").addEventListener("click", () => {
  sessionStorage.removeItem(TOKEN_KEY);
  $("forget-token").hidden = true;
  clearInterval(ui.poll); // nothing more is asked without a token
  leaveSession();
  ui.models.clear();
  ui.modelsShown = false;
  $("models").replaceChildren();
  $("sessions").tBodies[0].replaceChildren();
  $("session-count").textContent = "";
  askToken();
});

// ----- models ---------------------------------------------------------------------------------------------------
async function model(name) {
  if (!ui.models.has(name)) ui.models.set(name, await api("GET", `/models/${encodeURIComponent(name)}`));
  return ui.models.get(name);
}

function cell(row, text, cls) {
  const td = row.insertCell();
  td.textContent = text;
  if (cls) td.className = cls;
  return td;
}

async function renderModels() {
  const list = await api("GET", "/models");
  const box = $("models");
  box.replaceChildren();
  for (const summary of list.models) {
    const m = await model(summary.name);
    const div = document.createElement("div");
    div.className = "model";
    div.dataset.model = m.name;
    const title = document.createElement("h3");
    title.textContent = `${m.name} (${m.env_id}, statistic ${m.statistic}, K=${m.context_length})`;
    const table = document.createElement("table");
    table.createTHead().insertRow().append(
      ...["goal", "name", "mean", "std", "min", "max", "trajectories"].map((h) => {
        const th = document.createElement("th");
        th.textContent = h;
        return th;
      }),
    );
    const body = table.createTBody();
    for (const g of m.goals) {
      const row = body.insertRow();
      cell(row, g.id, "num");
      cell(row, g.name);
      for (const v of [g.mean, g.std, g.min, g.max]) cell(row, v.toFixed(3), "num");
      cell(row, g.count, "num");
    }
    div.append(title, table);
    box.append(div);
  }
}

// ----- sessions listing -----------------------------------------------------------------------------------------
const fmt = (v, digits, unit = "") => (v === null || v === undefined ? "–" : `${v.toFixed(digits)}${unit}`);

function sessionRow(s) {
  const row = document.createElement("tr");
  row.dataset.session = s.session_id;
  const link = document.createElement("a");
  link.href = `#/session/${encodeURIComponent(s.session_id)}`;
  link.textContent = s.session_id;
  row.insertCell().append(link);
  for (const cls of [null, "goal", "num step", "num", "num", null, "num"]) cell(row, "", cls);
  return row;
}

// Rows are updated in place, keyed by session id: a focused link or a click in progress survives each poll.
async function renderSessions() {
  let page = await api("GET", `/sessions?offset=${ui.offset}&limit=${PAGE}`);
  if (!page.sessions.length && page.total && ui.offset) {
    ui.offset = Math.floor((page.total - 1) / PAGE) * PAGE; // past the end after sessions closed: the last page
    page = await api("GET", `/sessions?offset=${ui.offset}&limit=${PAGE}`);
  }
  $("replica").textContent = `replica ${page.replica}`;
  const shown = page.sessions.length;
  $("session-count").textContent = shown
    ? `${page.offset + 1}–${page.offset + shown} of ${page.total}`
    : `none of ${page.total}`;
  const body = $("sessions").tBodies[0];
  const rows = new Map([...body.rows].map((r) => [r.dataset.session, r]));
  const listed = new Set(page.sessions.map((s) => s.session_id));
  for (const [id, row] of rows) if (!listed.has(id)) row.remove();
  page.sessions.forEach((s, i) => {
    const row = rows.get(s.session_id) ?? sessionRow(s);
    const texts = [
      s.model,
      `${s.goal} ${s.goal_name}`,
      String(s.step),
      fmt(s.acts_per_s, 1),
      fmt(s.last_latency_ms, 2, " ms"),
      s.served_by || "?",
      fmt(s.idle_s, 0, " s"),
    ];
    texts.forEach((t, j) => {
      const td = row.cells[j + 1];
      if (td.textContent !== t) td.textContent = t;
    });
    row.cells[2].dataset.goal = s.goal;
    if (body.rows[i] !== row) body.insertBefore(row, body.rows[i] ?? null); // a new row, or a new order
  });
  $("newer").disabled = ui.offset === 0;
  $("older").disabled = page.offset + shown >= page.total;
}

// The home page's refresh: the models once, then the listing; an error is shown and retried at the next poll.
async function refreshHome() {
  if (ui.polling) return; // the previous refresh has not answered yet
  ui.polling = true;
  try {
    if (!ui.modelsShown) {
      await renderModels();
      ui.modelsShown = true;
    }
    await renderSessions();
    show("");
  } catch (e) {
    show(e.message);
  } finally {
    ui.polling = false;
  }
}

$("newer").addEventListener("click", () => {
  ui.offset = Math.max(0, ui.offset - PAGE);
  renderSessions().catch((e) => show(e.message));
});
$("older").addEventListener("click", () => {
  ui.offset += PAGE;
  renderSessions().catch((e) => show(e.message));
});

// ----- charts (canvas, drawn by hand) ---------------------------------------------------------------------------
// Lines of `series` (arrays of [x, y]) over a shared x range; `labels` names y values (e.g. goal names).
function drawChart(canvas, series, { step = false, labels = null, marks = [] } = {}) {
  const ctx = canvas.getContext("2d");
  const w = canvas.width;
  const h = canvas.height;
  const pad = { l: 64, r: 8, t: 8, b: 18 };
  ctx.clearRect(0, 0, w, h);
  const points = series.flat();
  if (!points.length) return;
  let [x0, x1] = [Infinity, -Infinity];
  let [y0, y1] = [Infinity, -Infinity];
  for (const [x, y] of points) {
    x0 = Math.min(x0, x);
    x1 = Math.max(x1, x);
    y0 = Math.min(y0, y);
    y1 = Math.max(y1, y);
  }
  if (labels) [y0, y1] = [Math.min(y0, 0), Math.max(y1, labels.length - 1)];
  if (x1 === x0) x1 = x0 + 1;
  if (y1 === y0) [y0, y1] = [y0 - 1, y1 + 1];
  const X = (x) => pad.l + ((x - x0) / (x1 - x0)) * (w - pad.l - pad.r);
  const Y = (y) => h - pad.b - ((y - y0) / (y1 - y0)) * (h - pad.t - pad.b);
  ctx.font = "11px system-ui, sans-serif";
  ctx.fillStyle = "#57606a";
  ctx.strokeStyle = "#d8dee4";
  ctx.beginPath();
  ctx.moveTo(pad.l, pad.t);
  ctx.lineTo(pad.l, h - pad.b);
  ctx.lineTo(w - pad.r, h - pad.b);
  ctx.stroke();
  const ticks = labels ? labels.map((text, i) => [i, text]) : [[y0, y0.toFixed(2)], [y1, y1.toFixed(2)]];
  for (const [y, text] of ticks) ctx.fillText(String(text).slice(0, 10), 2, Y(y) + 4);
  ctx.fillText(`step ${x0}`, pad.l, h - 4);
  ctx.fillText(`${x1}`, w - pad.r - 40, h - 4);
  for (const [x, text] of marks) {
    ctx.strokeStyle = "#8c959f";
    ctx.setLineDash([3, 3]);
    ctx.beginPath();
    ctx.moveTo(X(x), pad.t);
    ctx.lineTo(X(x), h - pad.b);
    ctx.stroke();
    ctx.setLineDash([]);
    ctx.fillText(text, X(x) + 3, pad.t + 10);
  }
  series.forEach((line, i) => {
    ctx.strokeStyle = COLORS[i % COLORS.length];
    ctx.beginPath();
    line.forEach(([x, y], j) => {
      if (j === 0) ctx.moveTo(X(x), Y(y));
      else {
        if (step) ctx.lineTo(X(x), Y(line[j - 1][1]));
        ctx.lineTo(X(x), Y(y));
      }
    });
    ctx.stroke();
  });
}

// ----- one session ----------------------------------------------------------------------------------------------
function newView(id) {
  return { id, spec: null, actions: [], goals: [], rewards: [], marks: [], stream: new AbortController(), dirty: false };
}

function setState(v, s) {
  $("s-goal").textContent = `${s.goal} ${s.goal_name}`;
  $("s-goal").dataset.goal = s.goal;
  $("s-step").textContent = s.step;
  for (const b of $("goal-buttons").children) {
    const current = Number(b.dataset.goalId) === s.goal;
    b.classList.toggle("current", current);
    b.setAttribute("aria-pressed", String(current)); // the goal pursued, for screen readers too
  }
}

function onEvent(v, kind, d) {
  if (kind === "session") {
    show(""); // the stream is (re)connected: an earlier error no longer holds
    setState(v, d);
  }
  else if (kind === "act") {
    const action = Array.isArray(d.action) ? d.action : [d.action];
    v.actions.push([d.step, action]);
    v.goals.push([d.step, d.goal]);
    if (typeof d.reward === "number") v.rewards.push([d.reward_step ?? d.step, d.reward]);
    for (const list of [v.actions, v.goals, v.rewards]) if (list.length > HISTORY) list.splice(0, list.length - HISTORY);
    const goalName = v.spec.goals.find((g) => g.id === d.goal)?.name ?? "";
    setState(v, { goal: d.goal, goal_name: goalName, step: d.step + 1 });
    $("s-state").textContent = `last act ${d.latency_ms.toFixed(2)} ms in the server`;
  } else if (kind === "goal" || kind === "reset") {
    v.marks.push([d.step, `${kind} ${d.goal_name}`]);
    const g = v.spec.goals.find((g) => g.id === d.goal);
    if (g) $("target").value = g.mean; // the slider shows the goal now pursued
    $("target-value").textContent = Number($("target").value).toFixed(2);
    if (kind === "reset") v.actions.length = v.goals.length = v.rewards.length = 0;
    setState(v, d);
  } else if (kind === "dropped") $("s-state").textContent = `${d.count} events dropped (slow page)`;
  else if (kind === "closed" || kind === "expired") {
    $("s-state").textContent = `session ${kind}`;
    $("controls").hidden = true;
  }
  v.dirty = true;
}

function drawSession(v) {
  if (ui.view !== v) return;
  if (v.dirty) {
    v.dirty = false;
    const minStep = v.actions.length ? v.actions[0][0] : 0;
    const marks = v.marks.filter(([s]) => s >= minStep);
    const dims = v.actions.length ? v.actions[0][1].length : 0;
    const lines = Array.from({ length: dims }, (_, i) => v.actions.map(([s, a]) => [s, a[i]]));
    drawChart($("chart-actions"), lines, { marks });
    drawChart($("chart-goal"), [v.goals], { step: true, labels: v.spec.goals.map((g) => g.name), marks });
    const hasReward = v.rewards.length > 0;
    $("reward-title").hidden = $("chart-reward").hidden = !hasReward;
    if (hasReward) drawChart($("chart-reward"), [v.rewards], { marks });
  }
  requestAnimationFrame(() => drawSession(v));
}

async function follow(v) {
  while (ui.view === v) {
    try {
      await readEvents(`/sessions/${encodeURIComponent(v.id)}/events`, (k, d) => onEvent(v, k, d), v.stream.signal);
      if ($("controls").hidden) return; // closed or expired: the stream ended for good
    } catch (e) {
      if (v.stream.signal.aborted) return;
      show(`event stream: ${e.message}`);
      if (e.message.startsWith("not_found")) {
        $("controls").hidden = true; // nothing left to steer
        return;
      }
    }
    await new Promise((resolve) => setTimeout(resolve, 2000)); // reconnect after a broken stream
  }
}

async function openSession(id) {
  const v = newView(id);
  ui.view = v;
  $("s-id").textContent = id;
  $("controls").hidden = true; // shown once the session is found: never another session's buttons
  $("goal-buttons").replaceChildren();
  for (const f of ["s-model", "s-goal", "s-step", "s-state"]) $(f).textContent = "";
  for (const c of ["chart-actions", "chart-goal", "chart-reward"]) drawChart($(c), []);
  const s = await api("GET", `/sessions/${encodeURIComponent(id)}`);
  if (ui.view !== v) return; // the page moved on meanwhile
  v.spec = await model(s.model);
  $("s-model").textContent = s.model;
  $("s-statistic").textContent = v.spec.statistic;
  const buttons = v.spec.goals.map((g) => {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = `${g.name} (${g.mean.toFixed(2)})`;
    b.dataset.goal = g.name;
    b.dataset.goalId = g.id;
    b.addEventListener("click", () => command("PUT", "goal", { goal: g.name }));
    return b;
  });
  $("goal-buttons").replaceChildren(...buttons);
  const means = v.spec.goals.map((g) => g.mean);
  const [lo, hi] = [Math.min(...means), Math.max(...means)];
  const slider = $("target");
  const current = v.spec.goals.find((g) => g.id === s.goal);
  Object.assign(slider, { min: lo, max: hi, step: (hi - lo) / 100 || 0.01, value: current ? current.mean : lo });
  $("target-value").textContent = Number(slider.value).toFixed(2);
  setState(v, s);
  $("controls").hidden = false;
  $("s-state").textContent = "waiting for the next act";
  follow(v);
  drawSession(v);
}

$("target").addEventListener("input", () => {
  $("target-value").textContent = Number($("target").value).toFixed(2);
});
$("set-target").addEventListener("click", () => command("PUT", "goal", { target: Number($("target").value) }));
$("reset").addEventListener("click", () => command("POST", "reset", {}));
$("close").addEventListener("click", () => command("DELETE", ""));

async function command(method, what, body) {
  const v = ui.view;
  const path = `/sessions/${encodeURIComponent(v.id)}${what ? `/${what}` : ""}`;
  try {
    const s = await api(method, path, body);
    show("");
    if (s) setState(v, s);
    else {
      $("s-state").textContent = "session closed";
      $("controls").hidden = true;
    }
  } catch (e) {
    show(e.message);
  }
}

// ----- pages ----------------------------------------------------------------------------------------------------
function leaveSession() {
  if (ui.view) ui.view.stream.abort();
  ui.view = null;
}

async function route() {
  clearInterval(ui.poll);
  leaveSession();
  const m = location.hash.match(/^#\/session\/(.+)$/);
  $("home").hidden = !!m;
  $("session").hidden = !m;
  try {
    if (m) await openSession(decodeURIComponent(m[1]));
    else {
      ui.poll = setInterval(refreshHome, POLL_MS); // first: a failed refresh is retried at the next poll
      await refreshHome();
    }
    $("forget-token").hidden = !sessionStorage.getItem(TOKEN_KEY);
  } catch (e) {
    show(e.message);
  }
}

window.addEventListener("hashchange", route);
route();
