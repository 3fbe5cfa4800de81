// estop dashboard: draws the server's snapshots (server-sent events from /events).
// The page watches its own feed: 500 ms without an update (the server sends one at least
// every 200 ms) or a closed connection, and it says it lost the feed instead of showing an
// old state. Every state it shows is noted in window.estopShown with the frame's time and
// the moment it was drawn (the browser tests time the page with it).
"use strict";

const FEED_QUIET_MS = 500;
const shown = [];
window.estopShown = shown;
window.estopRenderErrors = 0;
window.estopUpdates = 0;  // updates received, and when (the benchmark counts them)
window.estopUpdateTimes = [];  // [received (ms, the page's clock), sent (s, the server's)]
let lastUpdate = 0;       // performance.now() of the latest update
let lastUpdateWall = 0;   // Date.now() of the same
let feedLost = true;
let current = "";         // "state|reason" on screen
let snap = null;

const $ = (id) => document.getElementById(id);

function fmtTime(t) {
  if (t === null || t === undefined) return "-";
  const d = new Date(t * 1000);
  const pad = (n, w) => String(n).padStart(w, "0");
  return `${pad(d.getHours(), 2)}:${pad(d.getMinutes(), 2)}:${pad(d.getSeconds(), 2)}` +
         `.${pad(d.getMilliseconds(), 3)}`;
}

function cls(state) { return String(state).replace(/[^A-Z]/g, ""); }

function note(state, reason, frameT, sentT) {
  const key = state + "|" + reason;
  if (key === current) return;
  current = key;
  shown.push({ state: state, reason: reason, frame_t: frameT, sent: sentT,
               shown: Date.now() / 1000 });
  if (shown.length > 200) shown.shift();
}

function showState(state, reason, detail, klass, frameT, sentT) {
  const banner = $("banner");
  banner.className = "state-" + klass;
  banner.dataset.state = state;
  $("state").textContent = state;
  $("reason").textContent = reason;
  $("detail").textContent = detail;
  note(state, reason, frameT, sentT);
}

function setLost(why) {
  if (feedLost && $("banner").dataset.state === "LOST FEED") return;
  feedLost = true;
  const feed = $("feed");
  feed.className = "feed-lost";
  feed.textContent = "LOST FEED: " + why;
  showState("LOST FEED", "state unknown", "the dashboard's server is not answering (" + why +
            "); last update " + fmtTime(lastUpdateWall / 1000), "LOST",
            lastUpdateWall ? lastUpdateWall / 1000 : null);
}

function rows(table, list) {
  // list: [[label, value, bad?], ...]
  const body = document.createElement("tbody");
  for (const r of list) {
    const tr = document.createElement("tr");
    if (r[2]) tr.className = "bad";
    const a = document.createElement("td");
    a.textContent = r[0];
    const b = document.createElement("td");
    b.className = "num";
    b.textContent = r[1] === null || r[1] === undefined ? "-" : String(r[1]);
    if (r[3]) b.title = r[3];
    tr.append(a, b);
    body.append(tr);
  }
  table.replaceChildren(body);
}

function render(s) {
  snap = s;
  const feed = $("feed");
  feed.className = "feed-ok";
  feed.textContent = "feed: live " + fmtTime(s.now);
  let detail;
  if (s.state === "NO SIGNAL") {
    detail = s.why + " - the brake controller brakes by itself";
  } else {
    detail = "brake: " + s.brake + (s.degraded ? " | LINK DEGRADED" : "") +
             " | since " + fmtTime(s.t);
  }
  showState(s.state, s.reason || "", detail, cls(s.state), s.t, s.now);

  const h = s.health;
  const list = [["frames (good)", `${h.frames} (${h.accepted})`],
                ["period", h.period_ms === null ? null : h.period_ms + " ms"],
                ["longest gap (last 100)", h.worst_gap_ms === null ? null : h.worst_gap_ms + " ms",
                 h.worst_gap_ms !== null && h.worst_gap_ms >= 50]];
  for (const [k, v] of Object.entries(h.errors)) list.push([k.replace(/_/g, " "), v, v > 0]);
  if (h.last_error) list.push(["last", h.last_error, true]);
  rows($("health"), list);

  rows($("status"), s.status.map((f) => [
    f.name.replace(/_/g, " ") + (f.total === null ? "" : " (total)"),
    f.value === null ? null : f.value + (f.unit && /^[\d.]+$/.test(f.value) ? " " + f.unit : "") +
      (f.total === null ? "" : ` (${f.total})`),
    (f.name === "invalid_packets" || f.name === "auth_failures") && f.total > 0,
    f.comment]));

  renderLink(s.link, s.unit);
  renderTimeline(s.timeline);
  const stops = Object.entries(s.stops);
  rows($("stops"), stops.length ? stops.map(([k, v]) => [k, v]) : [["none", 0]]);
  const i = s.inputs;
  const inputs = [["can-log lines (bad)", `${i.can_lines} (${i.can_bad})`, i.can_bad > 0],
                  ["log lines (not JSON)", `${i.log_lines} (${i.log_bad})`, i.log_bad > 0]];
  if (i.link_bad) inputs.push(["bad link_histogram", i.link_bad, true]);
  if (i.last_bad) inputs.push(["last bad", i.last_bad, true]);
  for (const n of i.notes) inputs.push(["note", n, false]);
  rows($("inputs"), inputs);
  $("stop").hidden = !s.allow_stop;
}

function renderTimeline(list) {
  const body = $("timeline").tBodies[0];
  const trs = list.map((c) => {
    const tr = document.createElement("tr");
    const cells = [fmtTime(c.t), c.state, c.reason, c.cause, c.src ? c.src + " (" + c.source +
                   ")" : c.source];
    cells.forEach((text, n) => {
      const td = document.createElement("td");
      if (n === 1) {
        const chip = document.createElement("span");
        chip.className = "chip " + cls(text);
        chip.textContent = text;
        td.append(chip);
      } else {
        td.textContent = text || "";
      }
      tr.append(td);
    });
    return tr;
  });
  body.replaceChildren(...trs);
}

const SVGNS = "http://www.w3.org/2000/svg";
function svg(tag, attrs, text) {
  const el = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
  if (text !== undefined) el.textContent = text;
  return el;
}

function renderLink(link, unit) {
  const plot = $("hist");
  const table = $("link");
  if (!link) {
    plot.replaceChildren(svg("text", { x: 10, y: 70 }, "waiting for a link_histogram event " +
                                                           "(estopd writes one every 10 s)"));
    rows(table, []);
    return;
  }
  // bars: one per bin, height by log10(count + 1); marks at S and T
  const n = link.counts.length;
  const W = 400, H = 120, x0 = 15, bw = n ? W / n : W;
  const top = Math.max(1, ...link.counts.map((c) => Math.log10(c + 1)));
  const els = [svg("line", { x1: x0, y1: H, x2: x0 + W, y2: H, class: "axis" })];
  link.counts.forEach((c, j) => {
    const h = (Math.log10(c + 1) / top) * (H - 10);
    els.push(svg("rect", { x: x0 + j * bw + 1, y: H - h, width: Math.max(1, bw - 2),
                           height: h, class: "bar" }));
  });
  const xAt = (us) => {
    const e = link.edges_us;
    for (let j = e.length - 1; j >= 0; j--) {
      if (us >= e[j]) {
        const hi = j + 1 < e.length ? e[j + 1] : e[j] * 2;
        return x0 + (j + (us - e[j]) / Math.max(1, hi - e[j])) * bw;
      }
    }
    return x0;
  };
  for (const [label, us] of [["10 ms", 1e4], ["100 ms", 1e5], ["1 s", 1e6]]) {
    els.push(svg("text", { x: xAt(us) - 10, y: H + 14 }, label));
  }
  for (const [name, ms] of [["S", unit.slow_ms], ["T", unit.timeout_ms]]) {
    if (typeof ms === "number") {
      const x = xAt(ms * 1000);
      els.push(svg("line", { x1: x, y1: 5, x2: x, y2: H, class: "mark-" + name }));
      els.push(svg("text", { x: x + 3, y: 14 }, name));
    }
  }
  els.push(svg("text", { x: x0, y: H + 28 }, "gaps between valid control packets (log scale)"));
  plot.replaceChildren(...els);
  const list = [];
  if (link.error) list.push(["fit", link.error, true]);
  else {
    list.push(["loss", (link.loss * 100).toFixed(2) + " %"]);
    list.push(["mean burst", link.mean_burst === null ? "no bursts" :
               link.mean_burst.toFixed(2) + " packets"]);
    for (const r of link.rows) {
      const range = r.low === null ? "" : ` (${r.low}..${r.high})`;
      const rec = r.recorded === null ? "" : `; unit counted ${r.recorded}`;
      list.push([`${r.what}/h at ${r.time_ms} ms`, `${r.model_per_hour}${range}${rec}`,
                 r.verdict === "more_than_model"]);
    }
  }
  rows(table, list);
}

function connect() {
  const es = new EventSource("/events");
  es.onmessage = (e) => {
    window.estopUpdates += 1;
    lastUpdate = performance.now();
    const times = window.estopUpdateTimes;
    times.push([lastUpdate, null]);
    if (times.length > 2000) times.shift();
    lastUpdateWall = Date.now();
    feedLost = false;
    let s;
    try {
      s = JSON.parse(e.data);
      window.estopUpdateTimes[window.estopUpdateTimes.length - 1][1] = s.now;
      render(s);
    } catch (err) {
      window.estopRenderErrors += 1;  // a bad update never freezes the page
    }
  };
  es.onerror = () => {
    if (es.readyState !== EventSource.OPEN) setLost("connection closed");
  };
}

setInterval(() => {
  if (!feedLost && performance.now() - lastUpdate > FEED_QUIET_MS) {
    setLost("no update for " + Math.round(performance.now() - lastUpdate) + " ms");
  }
}, 50);

$("stop").addEventListener("click", async () => {
  const out = $("stop-result");
  out.textContent = "stopping...";
  try {
    const r = await fetch("/stop", { method: "POST", headers: { "X-Estop-Stop": "1" } });
    const body = await r.json().catch(() => ({ outcome: r.statusText }));
    out.textContent = body.outcome;
  } catch (err) {
    out.textContent = "STOP could not reach the dashboard's server: " + err;
  }
});

connect();
