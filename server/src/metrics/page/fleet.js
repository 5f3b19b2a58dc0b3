// The fleet page: fetches the JSON snapshot (api/fleet, relative so that the page works behind a
// path prefix) two seconds after the previous one was rendered, one fetch at a time, and renders
// it. No framework, no build step, nothing fetched
// from elsewhere. Every value shown is also set as the element's data-value, unformatted.
"use strict";

const REFRESH_MS = 2000;
const $ = (id) => document.getElementById(id);

function ms(seconds) {
  return seconds === null || seconds === undefined ? "–" : (seconds * 1000).toFixed(1) + " ms";
}

function show(id, value, text) {
  const el = $(id);
  el.dataset.value = value === null || value === undefined ? "" : String(value);
  el.textContent = text === undefined ? String(value) : text;
}

function badge(id, ok, yes, no) {
  const el = $(id);
  el.textContent = ok ? yes : no;
  el.className = "badge " + (ok ? "ok" : "bad");
  el.dataset.value = String(ok);
}

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text;
  if (cls) td.className = cls;
  row.appendChild(td);
  return td;
}

function fill(tableId, rows, empty, render) {
  const body = $(tableId).tBodies[0];
  body.replaceChildren();
  if (rows.length === 0) {
    const tr = document.createElement("tr");
    tr.className = "empty";
    const td = cell(tr, empty);
    td.colSpan = $(tableId).tHead.rows[0].cells.length;
    body.appendChild(tr);
    return;
  }
  for (const row of rows) {
    const tr = document.createElement("tr");
    render(tr, row);
    body.appendChild(tr);
  }
}

function duration(seconds) {
  const s = Math.floor(seconds);
  if (s < 120) return s + " s";
  if (s < 7200) return Math.floor(s / 60) + " min";
  return Math.floor(s / 3600) + " h";
}

function setupCanvas(canvas) {
  const ctx = canvas.getContext("2d");
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  ctx.font = "11px system-ui, sans-serif";
  return ctx;
}

function niceMax(v) {
  if (!(v > 0)) return 1;
  const p = Math.pow(10, Math.floor(Math.log10(v)));
  // Multiples that divide into four round ticks.
  for (const m of [1, 2, 4, 6, 8, 10]) if (v <= m * p) return m * p;
  return 10 * p;
}

function axes(ctx, w, h, pad, max, unit) {
  ctx.strokeStyle = "#d9dee7";
  ctx.fillStyle = "#5d6677";
  ctx.lineWidth = 1;
  for (let i = 0; i <= 4; i++) {
    const y = pad.t + (h - pad.t - pad.b) * (1 - i / 4);
    ctx.beginPath();
    ctx.moveTo(pad.l, y);
    ctx.lineTo(w - pad.r, y);
    ctx.stroke();
    const label = (max * i / 4).toFixed(max < 4 ? 2 : 0) + unit;
    ctx.fillText(label, 4, y + 4);
  }
}

function drawLatency(history) {
  const canvas = $("latency-chart");
  const ctx = setupCanvas(canvas);
  const w = canvas.width, h = canvas.height, pad = { l: 52, r: 10, t: 10, b: 22 };
  const points = history.filter((p) => p.p99 !== null);
  const max = niceMax(Math.max(0, ...points.map((p) => p.p99 * 1000)));
  axes(ctx, w, h, pad, max, " ms");
  const x = (ago) => pad.l + (w - pad.l - pad.r) * (1 + ago / 60);
  const y = (v) => pad.t + (h - pad.t - pad.b) * (1 - v / max);
  ctx.fillStyle = "#5d6677";
  ctx.fillText("−60 s", pad.l, h - 6);
  ctx.fillText("now", w - pad.r - 22, h - 6);
  canvas.dataset.points = String(points.length);
  if (points.length === 0) {
    ctx.fillText("no rounds yet", w / 2 - 30, h / 2);
    return;
  }
  for (const [key, color] of [["p50", "#2f6fdf"], ["p99", "#e07a1f"]]) {
    ctx.strokeStyle = color;
    ctx.lineWidth = 2;
    ctx.beginPath();
    points.forEach((p, i) => {
      const px = x(Math.max(-60, p.seconds_ago)), py = y(p[key] * 1000);
      if (i === 0) ctx.moveTo(px, py); else ctx.lineTo(px, py);
    });
    ctx.stroke();
  }
  ctx.fillStyle = "#2f6fdf"; ctx.fillText("— p50", pad.l + 8, pad.t + 12);
  ctx.fillStyle = "#e07a1f"; ctx.fillText("— p99", pad.l + 52, pad.t + 12);
}

function drawHorizons(buckets) {
  const canvas = $("horizon-chart");
  const ctx = setupCanvas(canvas);
  const w = canvas.width, h = canvas.height, pad = { l: 52, r: 10, t: 10, b: 22 };
  const max = niceMax(Math.max(0, ...buckets.map((b) => b.count)));
  axes(ctx, w, h, pad, max, "");
  const n = buckets.length;
  const slot = (w - pad.l - pad.r) / n;
  let total = 0;
  buckets.forEach((b, i) => {
    total += b.count;
    const bh = (h - pad.t - pad.b) * (b.count / max);
    ctx.fillStyle = "#2f6fdf";
    ctx.fillRect(pad.l + i * slot + 2, h - pad.b - bh, slot - 4, bh);
    ctx.fillStyle = "#5d6677";
    const label = b.le === null ? ">" : "≤" + b.le;
    ctx.fillText(label, pad.l + i * slot + 2, h - 6);
  });
  canvas.dataset.rounds = String(total);
}

function render(s) {
  show("server-version", s.server.version);
  badge("server-ready", s.server.ready, "ready", "not ready");
  badge("driver-alive", s.server.driver_alive, "driver alive", "driver stopped");
  show("uptime", s.server.uptime_seconds, duration(s.server.uptime_seconds));
  show("robots-connected", s.robots.connected);
  show("robots-doors", s.robots.doors.length,
    s.robots.doors.map((d) => d.door + " " + d.connected + " of " + d.capacity).join(" · "));
  show("tasks-open", s.tasks.open);
  show("tasks-ended", s.tasks.ended_total);
  show("queue-depth", s.queue.depth);
  show("queue-running", s.queue.running);
  const mean = s.window.batch_size_mean;
  show("batch-mean", mean, mean === null ? "–" : mean.toFixed(1));
  show("rounds-rate", s.window.rounds_per_second, s.window.rounds_per_second.toFixed(1));
  show("rounds-answered", s.rounds.answered);
  show("rounds-failed", s.rounds.failed);
  for (const q of ["p50", "p90", "p99"]) {
    show("latency-" + q, s.window.latency_seconds[q], ms(s.window.latency_seconds[q]));
  }
  for (const el of document.querySelectorAll(".window-seconds")) {
    el.textContent = Math.round(s.window.seconds);
  }

  fill("engines", s.engines, "no engine", (tr, e) => {
    tr.dataset.engine = e.name;
    cell(tr, e.name);
    cell(tr, e.tier);
    cell(tr, e.remote ? "remote worker" : "local");
    cell(tr, e.state + (e.busy ? ", running a batch" : ""));
    const share = cell(tr, "");
    const bar = document.createElement("span");
    bar.className = "share";
    bar.style.width = Math.round(e.busy_share * 80) + "px";
    share.appendChild(bar);
    share.appendChild(document.createTextNode(Math.round(e.busy_share * 100) + " %"));
    share.dataset.value = String(e.busy_share);
    cell(tr, e.rtt_ms === null ? "–" : e.rtt_ms.toFixed(1) + " ms");
  });
  fill("refusals", s.refusals.filter((r) => r.total > 0), "none", (tr, r) => {
    cell(tr, r.door);
    cell(tr, r.reason);
    cell(tr, String(r.total), "num warn");
  });
  const lost = [];
  for (const [reason, total] of Object.entries(s.workers_removed_total)) {
    if (total > 0) lost.push(["removed from the pool", reason, total]);
  }
  for (const [reason, total] of Object.entries(s.redispatched_total)) {
    if (total > 0) lost.push(["rounds re-dispatched", reason, total]);
  }
  fill("workers-lost", lost, "none", (tr, [what, reason, total]) => {
    cell(tr, what);
    cell(tr, reason);
    cell(tr, String(total), "num");
  });
  fill("plugins", s.plugins, "no plugin loaded", (tr, p) => {
    tr.dataset.policy = p.policy;
    cell(tr, p.kind);
    cell(tr, p.policy);
    cell(tr, String(p.fallbacks), "num");
    cell(tr, p.quarantined ? "quarantined" : "healthy", p.quarantined ? "warn" : "");
  });
  fill("horizon-fallbacks", Object.entries(s.horizon_fallbacks), "none", (tr, [policy, n]) => {
    cell(tr, policy);
    cell(tr, String(n), "num");
  });
  drawLatency(s.latency_history);
  drawHorizons(s.window.horizon);
}

let snapshots = 0;

async function refresh() {
  try {
    const response = await fetch("api/fleet", { cache: "no-store" });
    if (!response.ok) throw new Error("api/fleet answered " + response.status);
    const snapshot = await response.json();
    render(snapshot);
    snapshots += 1;
    document.body.dataset.state = "live";
    document.body.dataset.snapshots = String(snapshots);
    show("updated", new Date().toLocaleTimeString(), "updated " + new Date().toLocaleTimeString());
  } catch (error) {
    document.body.dataset.state = "error";
    $("updated").textContent = "cannot read the snapshot: " + error.message;
  }
}

async function poll() {
  await refresh();
  setTimeout(poll, REFRESH_MS);
}

poll();
