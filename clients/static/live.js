// The live view of `gmt run --live`: frames as they render, the running statistic against the goal bands, and
// goal buttons (a click asks the run to change its session's goal through the policy server).
"use strict";

const KEEP = 1000; // steps on the chart
const COLORS = ["#0969da", "#cf222e", "#1a7f37", "#9a6700", "#8250df", "#bf3989", "#0550ae", "#6e7781"];
const $ = (id) => document.getElementById(id);
const live = { goals: [], points: [], goal: null, session: "", episode: 0, dirty: false };

const goalName = (id) => live.goals.find((g) => g.id === id)?.name ?? String(id);
const color = (id) => COLORS[live.goals.findIndex((g) => g.id === id) % COLORS.length];

function setGoal(id) {
  live.goal = id;
  for (const b of $("goals").children) b.classList.toggle("current", Number(b.dataset.goal) === id);
}

function status(step) {
  $("status").textContent =
    `episode ${live.episode + 1} · session ${live.session} · step ${step} · goal ${goalName(live.goal)}`;
  $("status").dataset.session = live.session;
}

async function askGoal(g) {
  $("goal-message").textContent = `asking for goal ${g.name}…`;
  try {
    const r = await fetch("/goal", {
      method: "POST",
      headers: { "Content-Type": "application/json" },
      body: JSON.stringify({ goal: g.id }),
    });
    const doc = await r.json();
    if (!r.ok) throw new Error(doc.error.message);
    $("goal-message").textContent = `goal ${doc.goal_name} from step ${doc.step}`;
  } catch (e) {
    $("goal-message").textContent = `goal not changed: ${e.message}`;
  }
}

function intro(d) {
  live.goals = d.goals;
  $("model").textContent = `${d.model} on ${d.env_id}`;
  $("transport").textContent = `policy server: ${d.transport}`;
  $("statistic").textContent = d.statistic;
  $("goals").replaceChildren(
    ...d.goals.map((g) => {
      const b = document.createElement("button");
      b.type = "button";
      b.dataset.goal = g.id;
      b.textContent = `${g.name} (${g.mean.toFixed(2)})`;
      b.style.background = `${color(g.id)}33`;
      b.addEventListener("click", () => askGoal(g));
      return b;
    }),
  );
}

function update(d) {
  for (const p of d.points) live.points.push(p);
  if (live.points.length > KEEP) live.points.splice(0, live.points.length - KEEP);
  const last = d.points[d.points.length - 1];
  if (last) {
    setGoal(last[1]);
    status(last[0]);
  }
  if (d.frame) {
    $("frame").src = d.frame.url;
    $("frame").dataset.step = d.frame.step;
    $("caption").textContent = `step ${d.frame.step} · goal ${goalName(d.frame.goal)}`;
  }
  live.dirty = true;
}

function draw() {
  requestAnimationFrame(draw);
  if (!live.dirty) return;
  live.dirty = false;
  const canvas = $("chart");
  const ctx = canvas.getContext("2d");
  const [w, h] = [canvas.width, canvas.height];
  const pad = { l: 48, r: 8, t: 8, b: 18 };
  ctx.clearRect(0, 0, w, h);
  const pts = live.points.filter((p) => p[2] !== null);
  let [y0, y1] = [Infinity, -Infinity];
  for (const g of live.goals) [y0, y1] = [Math.min(y0, g.mean - g.std), Math.max(y1, g.mean + g.std)];
  for (const p of pts) [y0, y1] = [Math.min(y0, p[2]), Math.max(y1, p[2])];
  if (!Number.isFinite(y0)) return;
  if (y1 === y0) [y0, y1] = [y0 - 1, y1 + 1];
  const x0 = pts.length ? pts[0][0] : 0;
  const x1 = Math.max(pts.length ? pts[pts.length - 1][0] : 1, x0 + 1);
  const X = (x) => pad.l + ((x - x0) / (x1 - x0)) * (w - pad.l - pad.r);
  const Y = (y) => h - pad.b - ((y - y0) / (y1 - y0)) * (h - pad.t - pad.b);
  ctx.font = "11px system-ui, sans-serif";
  for (const g of live.goals) {
    ctx.fillStyle = `${color(g.id)}${g.id === live.goal ? "55" : "1c"}`;
    ctx.fillRect(pad.l, Y(g.mean + g.std), w - pad.l - pad.r, Y(g.mean - g.std) - Y(g.mean + g.std));
    ctx.fillStyle = color(g.id);
    ctx.fillText(g.name, 2, Y(g.mean) + 4);
  }
  ctx.fillStyle = "#57606a";
  ctx.fillText(`step ${x0}`, pad.l, h - 4);
  ctx.fillText(`${x1}`, w - pad.r - 40, h - 4);
  ctx.lineWidth = 2;
  for (let i = 1; i < pts.length; i++) {
    ctx.strokeStyle = color(pts[i][1]);
    ctx.beginPath();
    ctx.moveTo(X(pts[i - 1][0]), Y(pts[i - 1][2]));
    ctx.lineTo(X(pts[i][0]), Y(pts[i][2]));
    ctx.stroke();
  }
}

const events = new EventSource("/events");
events.addEventListener("intro", (e) => intro(JSON.parse(e.data)));
events.addEventListener("episode", (e) => {
  const d = JSON.parse(e.data);
  Object.assign(live, { episode: d.episode, session: d.session_id, points: [], dirty: true });
  status(0);
});
events.addEventListener("update", (e) => update(JSON.parse(e.data)));
events.addEventListener("end", () => {
  $("status").textContent += " · run finished";
  events.close();
});
requestAnimationFrame(draw);
