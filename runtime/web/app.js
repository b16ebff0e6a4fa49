// The live page: reads /events (Server-Sent Events, one JSON object per message) and draws.
// No library: plots are canvas polylines. The DOM carries what a test checks: the label shown
// and its seq (#label[data-seq]), the samples received (#samples), the breaks drawn for samples
// that never came (#samples[data-breaks]), the link's counters.
"use strict";

const SPAN_S = 10;           // seconds of each channel shown
const $ = (id) => document.getElementById(id);
const view = { channels: [], every: 1, rate: 100, points: 0, samples: 0, total: 0,
               marks: [], next: null, breaks: 0, dirty: false, ended: false };
// marks: {at, cut} for the plotted sample index `at` (of view.total): a vertical line there (a
// gap, a reconnect, a discontinuity); cut: the line is not drawn into it (samples are missing).
// Only the marks inside the plotted span are kept.

function setState(s) { document.body.dataset.state = s; $("state").textContent = s; }

function onHeader(h) {
  document.body.dataset.labels = h.labels === false ? "no" : "yes";
  view.rate = h.sample_rate_hz; view.every = h.every || 1;
  view.points = Math.max(2, Math.round(SPAN_S * view.rate / view.every));
  $("device").textContent = `${h.device} · ${h.sample_rate_hz} Hz · ${h.channels.length} channels`;
  const box = $("channels");
  box.textContent = "";
  view.channels = h.channels.map((c) => {
    const div = document.createElement("div");
    div.className = "chan";
    div.innerHTML = '<div class="title"><span class="name"></span><span class="value">-</span></div><canvas></canvas>';
    div.querySelector(".name").textContent = c.unit ? `${c.name} [${c.unit}]` : c.name;
    box.appendChild(div);
    return { name: c.name, unit: c.unit, data: new Float32Array(view.points), canvas: div.querySelector("canvas"),
             value: div.querySelector(".value") };
  });
  view.total = 0; view.marks = []; view.next = null;
}

function mark(cut) {
  const last = view.marks[view.marks.length - 1];
  if (last && last.at === view.total) { last.cut = last.cut || cut; return; }
  view.marks.push({ at: view.total, cut });
}

function onSamples(m) {
  if (!view.channels.length) return;
  // a seq other than the one expected: samples were lost (dropped messages, a gap, a restart)
  if (view.next !== null && m.seq !== view.next) {
    mark(true);
    view.breaks += 1;
    $("samples").dataset.breaks = view.breaks;
  }
  view.next = m.seq + m.values.length * (m.every || view.every);
  for (const row of m.values) {
    const i = view.total % view.points;
    view.channels.forEach((c, k) => { c.data[i] = row[k]; });
    view.total += 1;
  }
  while (view.marks.length && view.marks[0].at < view.total - view.points) view.marks.shift();
  view.samples += m.values.length;
  $("samples").textContent = view.samples;
  const last = m.values[m.values.length - 1];
  view.channels.forEach((c, k) => { c.value.textContent = fmt(last[k]) + (c.unit ? " " + c.unit : ""); });
  if (document.body.dataset.state !== "live") setState("live");
  redraw();
}

function fmt(v) { return Math.abs(v) >= 100 ? v.toFixed(1) : Math.abs(v) >= 1 ? v.toFixed(2) : v.toFixed(3); }

function onLabel(l) {
  const el = $("label");
  el.textContent = l.label;
  el.dataset.seq = l.seq;
  el.dataset.p = l.p;
  const smooth = l.smoothed ? ` · smoothed: ${l.smoothed}` : "";
  $("label-detail").textContent = `p ${l.p.toFixed(3)} · seq ${l.seq} · t ${l.t.toFixed(2)} s · ${l.latency_ms} ms${smooth}`;
  const probs = $("probs");
  probs.textContent = "";
  for (const [name, p] of Object.entries(l.probs)) {
    const row = document.createElement("div");
    row.className = "row" + (name === l.label ? " top" : "");
    row.innerHTML = '<span class="name"></span><span class="bar"><i></i></span><span class="p"></span>';
    row.querySelector(".name").textContent = name;
    row.querySelector("i").style.width = (100 * p).toFixed(1) + "%";
    row.querySelector(".p").textContent = p.toFixed(3);
    probs.appendChild(row);
  }
}

function onStatus(s) {
  const put = (id, v) => { if (v !== undefined) $(id).textContent = v; };
  put("rate", s.rate_hz); put("frames", s.frames); put("gaps", s.gaps); put("lost", s.samples_lost);
  put("crc", s.crc_errors); put("malformed", s.malformed); put("reconnects", s.reconnects);
  put("stalls", s.stalls); put("dropped", s.dropped);
}

function onEvent(e) {
  const li = document.createElement("li");
  const fields = Object.entries(e).filter(([k]) => k !== "event").map(([k, v]) => `${k}=${v}`).join(" ");
  li.textContent = `${e.event} ${fields}`;
  li.dataset.event = e.event;
  const list = $("events");
  list.insertBefore(li, list.firstChild);
  while (list.children.length > 50) list.removeChild(list.lastChild);
  if (e.event === "gap" || e.event === "reconnect") mark(false);
  if (e.event === "stall") setState("stalled");
  redraw();
}

function redraw() {
  if (view.dirty) return;
  view.dirty = true;
  requestAnimationFrame(draw);
}

function draw() {
  view.dirty = false;
  const n = Math.min(view.total, view.points);
  for (const c of view.channels) {
    const cv = c.canvas, dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(cv.clientWidth * dpr)), h = Math.max(1, Math.round(cv.clientHeight * dpr));
    if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
    const g = cv.getContext("2d");
    g.clearRect(0, 0, w, h);
    if (n < 2) continue;
    let lo = Infinity, hi = -Infinity;
    for (let j = 0; j < n; j++) { const v = c.data[(view.total - n + j) % view.points]; lo = Math.min(lo, v); hi = Math.max(hi, v); }
    if (hi - lo < 1e-9) { hi += 0.5; lo -= 0.5; }
    const x = (j) => (j + view.points - n) / (view.points - 1) * (w - 1);
    const y = (v) => h - 2 - (v - lo) / (hi - lo) * (h - 4);
    g.strokeStyle = "rgba(201, 72, 11, 0.45)"; g.lineWidth = dpr;
    const cuts = new Set();
    for (const m of view.marks) {
      const j = m.at - (view.total - n);
      if (m.cut) cuts.add(j);
      if (j >= 0 && j < n) { g.beginPath(); g.moveTo(x(j), 0); g.lineTo(x(j), h); g.stroke(); }
    }
    g.strokeStyle = "#2f6fdf"; g.lineWidth = 1.5 * dpr;
    g.beginPath();
    for (let j = 0; j < n; j++) {
      const v = c.data[(view.total - n + j) % view.points];
      if (j === 0 || cuts.has(j)) g.moveTo(x(j), y(v)); else g.lineTo(x(j), y(v));
    }
    g.stroke();
  }
}

function start() {
  $("span-s").textContent = SPAN_S;
  const es = new EventSource("events");
  es.onopen = () => { if (!view.ended) setState("live"); };
  es.onerror = () => { if (!view.ended) setState("reconnecting"); };
  es.onmessage = (msg) => {
    const m = JSON.parse(msg.data);
    $("samples").dataset.messages = (+($("samples").dataset.messages || 0) + 1);
    switch (m.event) {
      case undefined: onLabel(m); break;
      case "header": onHeader(m); break;
      case "samples": onSamples(m); break;
      case "status": onStatus(m); break;
      case "end": view.ended = true; es.close(); setState("ended"); break;
      default: onEvent(m);
    }
  };
  window.addEventListener("resize", redraw);
}

start();
