// The live page: reads /events (Server-Sent Events, one JSON object per message) and draws.
// No library: plots are canvas polylines. The DOM carries what a test checks: the label shown
// and its seq (#label[data-seq]; the stable label when the labels are post-processed, the raw
// one in #raw-label), the samples received (#samples), the breaks drawn for samples that never
// came (#samples[data-breaks]), the label strip's counts (#strip[data-windows], data-uncertain,
// data-gaps), the changes of the stable label (#changes li), the link's counters.
"use strict";

const SPAN_S = 10;           // seconds of each channel shown
const STRIP_S = 60;          // seconds of labels in the strip
// class colours, in the order of the model's classes (the label objects' `probs` keys)
const PALETTE = ["#2f6fdf", "#1c8a4a", "#1a9fb0", "#8a3fd1", "#d1493f", "#e8a317", "#7a8a1c",
                 "#d14f9c", "#5a6b85", "#8c5a2b"];
const UNCERTAIN_COLOUR = "#c4c9d1";  // no stable label: grey
const GAP_COLOUR = "#1d2430";        // a gap, a reconnection, a stall: a dark tick (then blank)
const $ = (id) => document.getElementById(id);
const view = { channels: [], every: 1, rate: 100, points: 0, samples: 0, total: 0,
               marks: [], next: null, breaks: 0, dirty: false, ended: false,
               classes: [], strip: [], lastT: null, hop: 0.25, timer: null };
// strip: {from, at (ms, the page's clock: at = arrival), label, kind: "label" | "uncertain"}
// for a window, drawn over the device time it covers before its arrival; {at, kind: "gap"}
// for a gap, reconnect or stall event.
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

function classColour(name) {
  const i = view.classes.indexOf(name);
  return i < 0 ? UNCERTAIN_COLOUR : PALETTE[i % PALETTE.length];
}

function legend() {
  const box = $("legend");
  box.textContent = "";
  const key = (name, colour, cls) => {
    const span = document.createElement("span");
    span.className = cls || "";
    span.dataset.class = name;
    span.innerHTML = "<i></i>";
    span.querySelector("i").style.background = colour;
    span.append(name);
    box.appendChild(span);
  };
  view.classes.forEach((c) => key(c, classColour(c)));
  if (document.body.dataset.smoothed === "yes") key("uncertain", UNCERTAIN_COLOUR);
  key("gap", GAP_COLOUR, "gap");
}

function onLabel(l, at = performance.now()) {
  const smoothed = l.smoothed !== undefined && l.smoothed !== null;
  const names = Object.keys(l.probs);
  const mode = smoothed ? "yes" : "no";
  if (names.join("\n") !== view.classes.join("\n") || document.body.dataset.smoothed !== mode) {
    view.classes = names;
    document.body.dataset.smoothed = mode;
    legend();
  }
  // shown large: the stable label (or "uncertain") when post-processed, else the raw label
  const shown = smoothed ? l.smoothed.label : l.label;
  const p = smoothed ? l.smoothed.p : l.p;
  const stable = smoothed ? l.stable : true;
  const el = $("label");
  el.textContent = shown;
  el.dataset.seq = l.seq;
  el.dataset.p = p;
  el.dataset.stable = stable;
  el.style.color = stable ? classColour(shown) : "";
  $("raw-label").textContent = l.label;
  $("raw-label").dataset.p = l.p;
  $("raw-p").textContent = `p ${l.p.toFixed(3)}`;
  const reset = l.reset ? ` · reset: ${l.reset}` : "";
  $("label-detail").textContent = `p ${p.toFixed(3)} · seq ${l.seq} · t ${l.t.toFixed(2)} s · ${l.latency_ms} ms${reset}`;
  const probs = $("probs");
  probs.textContent = "";
  for (const [name, q] of Object.entries(l.probs)) {
    const row = document.createElement("div");
    row.className = "row" + (name === l.label ? " top" : "");
    row.innerHTML = '<span class="name"></span><span class="bar"><i></i></span><span class="p"></span>';
    row.querySelector(".name").textContent = name;
    row.querySelector("i").style.width = (100 * q).toFixed(1) + "%";
    row.querySelector(".p").textContent = q.toFixed(3);
    probs.appendChild(row);
  }
  // the window covers the device time since the previous one (one hop), up to its arrival
  if (view.lastT !== null && !l.reset && l.t > view.lastT && l.t - view.lastT < 5) view.hop = l.t - view.lastT;
  view.lastT = l.t;
  view.strip.push({ from: at - 1000 * view.hop, at, label: shown, kind: stable ? "label" : "uncertain" });
  drawStrip(at);
}

function onChange(e) {
  const li = document.createElement("li");
  li.dataset.seq = e.seq;
  li.dataset.from = e.from === null ? "" : e.from;
  li.dataset.to = e.to;
  const swatch = document.createElement("i");
  swatch.style.background = classColour(e.to);
  li.append(swatch, `${e.t.toFixed(2)} s  ${e.from === null ? "(start)" : e.from} → ${e.to}`);
  const list = $("changes");
  list.insertBefore(li, list.firstChild);
  while (list.children.length > 20) list.removeChild(list.lastChild);
}

function drawStrip(now = performance.now()) {
  const span = STRIP_S * 1000, start = now - span;
  while (view.strip.length && view.strip[0].at < start - 5000) view.strip.shift();
  const cv = $("strip"), dpr = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(cv.clientWidth * dpr)), h = Math.max(1, Math.round(cv.clientHeight * dpr));
  if (cv.width !== w || cv.height !== h) { cv.width = w; cv.height = h; }
  const g = cv.getContext("2d");
  g.clearRect(0, 0, w, h);
  const x = (t) => (t - start) / span * w;
  let windows = 0, uncertain = 0, gaps = 0;
  for (const s of view.strip) {
    if (s.kind === "gap" || s.at < start || s.at > now) continue;
    windows += 1;
    if (s.kind === "uncertain") uncertain += 1;
    g.fillStyle = s.kind === "uncertain" ? UNCERTAIN_COLOUR : classColour(s.label);
    const x0 = Math.max(0, Math.floor(x(s.from))), x1 = Math.min(w, Math.ceil(x(s.at)));
    if (x1 > x0) g.fillRect(x0, 0, x1 - x0, h);
  }
  g.fillStyle = GAP_COLOUR;  // over the windows: a gap between two windows stays visible
  for (const s of view.strip) {
    if (s.kind !== "gap" || s.at < start || s.at > now) continue;
    gaps += 1;
    g.fillRect(Math.round(x(s.at)) - dpr, 0, 2 * dpr, h);
  }
  Object.assign(cv.dataset, { windows, uncertain, gaps });
}

function onStatus(s) {
  const put = (id, v) => { if (v !== undefined) $(id).textContent = v; };
  put("rate", s.rate_hz ?? "-"); put("frames", s.frames); put("gaps", s.gaps); put("lost", s.samples_lost);
  put("crc", s.crc_errors); put("malformed", s.malformed); put("reconnects", s.reconnects);
  put("stalls", s.stalls); put("dropped", s.dropped);
}

function onEvent(e, at = performance.now()) {
  if (e.event === "change") { onChange(e); return; }
  if (e.event === "gap" || e.event === "reconnect" || e.event === "stall" || e.event === "invalid") {
    view.strip.push({ at, kind: "gap" });
    drawStrip(at);
  }
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
  $("strip-s").textContent = STRIP_S;
  view.timer = setInterval(() => drawStrip(), 1000);  // the strip scrolls between windows
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
      case "end": view.ended = true; es.close(); clearInterval(view.timer); setState("ended"); break;
      default: onEvent(m);
    }
  };
  window.addEventListener("resize", () => { redraw(); drawStrip(); });
}

start();
