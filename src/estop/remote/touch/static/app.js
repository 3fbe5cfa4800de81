// The touch remote's page. A finger on the drive area is the dead-man: while at least one is
// there, a "held" frame (steering, gas) goes to the remote every control period; the last
// finger leaving, a touch the browser cancels, the page hidden, left or losing focus, says
// "lift" at once. The remote (estop remote --touch) holds the key and turns fresh frames into
// control packets; if this page stops (frozen, killed, its network gone) the frames stop and
// so do the packets. Messages are "MAC JSON" (see estop/remote/touch/wire.py); the pairing token is
// in the URL's fragment and never sent.
"use strict";

const NEUTRAL = 0.12;  // the middle of each axis, as a fraction of its half: no gas, no steering
const enc = new TextEncoder();
const $ = (id) => document.getElementById(id);
const drive = $("drive");

// For the tests and for anyone debugging in the browser: what the page did and drew.
const estop = window.estop = {
  shown: [],        // {state, reason, shown}: every state drawn, wall-clock seconds
  sent: [],         // {t, why, at}: the page's lifts and holds, wall-clock seconds
  renderErrors: 0, badMacs: 0, framesSent: 0,
};

function now() { return (performance.timeOrigin + performance.now()) / 1000; }

function readToken() {
  const k = new URLSearchParams(location.hash.slice(1)).get("k");
  if (!k) return null;
  try {
    const bin = atob(k.replace(/-/g, "+").replace(/_/g, "/"));
    const bytes = Uint8Array.from(bin, (c) => c.charCodeAt(0));
    return bytes.length === 16 ? bytes : null;
  } catch (e) {
    return null;
  }
}
const token = readToken();

// ---------------------------------------------------------------- the socket and its MACs
let ws = null;
let serverNonce = null;  // the server's: this page's messages are MACed with it
let pageNonce = null;    // this page's: the server's messages are MACed with it
let nOut = 0, nIn = 0, paired = false, refused = "";
let periodMs = 20;
let pingId = 0;
const pings = new Map();
let pageRtt = null;

function macOf(nonce, body) {
  const b = enc.encode(body);
  const data = new Uint8Array(nonce.length + b.length);
  data.set(nonce);
  data.set(b, nonce.length);
  return bytesToHex(blake2s(token, data, 16));
}

function send(msg) {
  if (!ws || ws.readyState !== WebSocket.OPEN) return false;
  if (token && serverNonce && (paired || msg.t === "pair")) {
    const body = JSON.stringify({ ...msg, n: ++nOut });
    ws.send(macOf(serverNonce, body) + " " + body);
  } else {
    ws.send("- " + JSON.stringify(msg));
  }
  return true;
}

function receive(text) {
  const sp = text.indexOf(" ");
  const tag = text.slice(0, sp), body = text.slice(sp + 1);
  const msg = JSON.parse(body);
  if (paired) {  // from the pairing on, every message of the server must verify
    if (tag !== macOf(pageNonce, body) || !(msg.n > nIn)) { estop.badMacs++; return null; }
    nIn = msg.n;
  } else if (tag !== "-" && msg.t !== "paired") {
    estop.badMacs++; return null;
  } else if (msg.t === "paired") {
    if (!pageNonce || tag !== macOf(pageNonce, body)) { estop.badMacs++; return null; }
    nIn = msg.n;
  }
  return msg;
}

function connect() {
  const url = (location.protocol === "https:" ? "wss://" : "ws://") + location.host + "/ws";
  ws = new WebSocket(url);
  ws.onmessage = (ev) => {
    let msg;
    try { msg = receive(ev.data); } catch (e) { estop.renderErrors++; return; }
    if (msg) handle(msg);
  };
  ws.onclose = () => {
    // the remote lifts a hold of this page when its socket closes; the page forgets its
    // fingers, so that driving needs a new touch once the remote is back
    voidTouches();
    stopHold(null);
    ws = null; paired = false; serverNonce = null; nOut = 0; nIn = 0;
    show({ state: "NO REMOTE", reason: "connection to estop remote lost", cls: "unreachable" });
    setText("hold", "not driving: the unit stops (lift, or silence)");
    setTimeout(connect, 1000);
  };
}

function handle(msg) {
  switch (msg.t) {
    case "hello":
      serverNonce = hexToBytes(msg.nonce);
      periodMs = msg.period_ms;
      if (token) {
        pageNonce = crypto.getRandomValues(new Uint8Array(16));
        send({ t: "pair", nonce: bytesToHex(pageNonce) });
      } else {
        refused = "no pairing token: STOP only";
      }
      ping();
      break;
    case "paired": paired = true; refused = ""; note("paired with estop remote"); ping(); break;
    case "refused":
      if (msg.what === "pair") refused = msg.why + ": STOP only";
      note(msg.what + " refused: " + msg.why, true);
      break;
    case "state": drawState(msg); break;
    case "reply": note(msg.what.toUpperCase() + ": " + msg.line, !msg.ok); break;
    case "pong":
      if (pings.has(msg.id)) { pageRtt = performance.now() - pings.get(msg.id); pings.delete(msg.id); }
      break;
  }
}

function ping() {
  if (!ws || ws.readyState !== WebSocket.OPEN || !serverNonce) return;
  pings.set(++pingId, performance.now());
  if (pings.size > 10) pings.delete(pings.keys().next().value);
  send({ t: "ping", id: pingId });
}
setInterval(ping, 1000);

// ---------------------------------------------------------------- the dead-man
const touches = new Map();   // identifier -> {x, y}: fingers that drive, oldest first
const voided = new Set();    // fingers still down from before a page-level lift: ignored
let timer = null;
let tilt = null;             // steering from the device's tilt, when chosen and given

function axis(v) {
  const a = Math.abs(v);
  if (a <= NEUTRAL) return 0;
  return Math.round(Math.sign(v) * Math.min(1, (a - NEUTRAL) / (1 - NEUTRAL)) * 1000) / 1000;
}

// The drive area's box, read once per layout change: reading it on every frame would force a
// layout each period, and the page's thread must stay free for the touchend that lifts.
let area = null;
function driveBox() {
  if (!area) area = drive.getBoundingClientRect();
  return area;
}
new ResizeObserver(() => { area = null; }).observe(drive);
window.addEventListener("resize", () => { area = null; });

function control() {
  const first = touches.values().next().value;
  const r = driveBox();
  const x = (first.x - (r.left + r.width / 2)) / (r.width / 2);
  const y = ((r.top + r.height / 2) - first.y) / (r.height / 2);
  const steer = ($("tilt").checked && tilt !== null) ? tilt : axis(x);
  return { steer, gas: axis(y) };
}

function sendHeld() {
  if (!touches.size) return;
  const c = control();
  if (paired && send({ t: "held", at: performance.now(), steer: c.steer, gas: c.gas })) {
    estop.framesSent++;
  }
}

function startHold() {
  if (timer !== null) return;
  estop.sent.push({ t: "hold", at: now() });
  sendHeld();
  timer = setInterval(sendHeld, periodMs);
  drive.classList.add("held");
}

function stopHold(why, ev) {
  if (timer === null) return;
  clearInterval(timer);
  timer = null;
  drive.classList.remove("held");
  $("finger").hidden = true;
  fingerAt = "";
  if (why) {
    const t = now();
    send({ t: "lift", why });
    // queued: how long the event waited for this page's thread (from the browser's stamp)
    const queued = ev && ev.timeStamp ? performance.now() - ev.timeStamp : null;
    estop.sent.push({ t: "lift", why, at: t, queued, sent: now() });
  }
}

function voidTouches() {
  for (const id of touches.keys()) voided.add(id);
  touches.clear();
}

// the page going away or out of sight ends the hold at once, and the fingers still down
// count no more: a new touch is needed
function pageLift(ev) {
  if (ev.type === "visibilitychange" && document.visibilityState !== "hidden") return;
  if (!touches.size && timer === null) return;
  voidTouches();
  stopHold(ev.type);
}
document.addEventListener("visibilitychange", pageLift);
window.addEventListener("pagehide", pageLift);
window.addEventListener("blur", pageLift);
document.addEventListener("freeze", pageLift);

function fingerDown(id, x, y) {
  voided.delete(id);
  touches.set(id, { x, y });
  startHold();
  drawFinger();
}

function fingerUp(id, why, ev) {
  if (voided.delete(id) || !touches.delete(id)) return;
  if (!touches.size) stopHold(why, ev);
  else drawFinger();
}

drive.addEventListener("touchstart", (ev) => {
  ev.preventDefault();
  for (const t of ev.changedTouches) fingerDown(t.identifier, t.clientX, t.clientY);
}, { passive: false });
drive.addEventListener("touchmove", (ev) => {
  ev.preventDefault();
  for (const t of ev.changedTouches) {
    if (touches.has(t.identifier)) touches.set(t.identifier, { x: t.clientX, y: t.clientY });
  }
  if (touches.size) drawFinger();
}, { passive: false });
for (const type of ["touchend", "touchcancel"]) {
  drive.addEventListener(type, (ev) => {
    ev.preventDefault();
    for (const t of ev.changedTouches) fingerUp(t.identifier, type, ev);
  }, { passive: false });
}
// a mouse held down on the drive area counts as a finger (a laptop without a touch screen)
drive.addEventListener("mousedown", (ev) => {
  if (ev.button === 0) fingerDown("mouse", ev.clientX, ev.clientY);
});
window.addEventListener("mousemove", (ev) => {
  if (touches.has("mouse")) touches.set("mouse", { x: ev.clientX, y: ev.clientY });
});
window.addEventListener("mouseup", (ev) => { if (ev.button === 0) fingerUp("mouse", "mouseup"); });

let fingerAt = "";
function drawFinger() {  // on touches only, and moved by a transform: no repaint of the area
  const f = $("finger");
  const first = touches.values().next().value;
  if (!first) { f.hidden = true; fingerAt = ""; return; }
  const r = driveBox();
  const at = "translate(" + (first.x - r.left) + "px, " + (first.y - r.top) + "px)";
  if (at !== fingerAt) { f.style.transform = at; fingerAt = at; }
  f.hidden = false;
}

// ---------------------------------------------------------------- buttons
function press(id, fn) {
  $(id).addEventListener("pointerdown", (ev) => { ev.preventDefault(); fn(ev); });
}
press("stop", () => {
  if (send({ t: "stop" })) note("STOP sent: waiting for the unit's answer");
  else note("STOP NOT SENT: no connection to estop remote", true);
});
press("release", () => { if (send({ t: "release" })) note("RELEASE sent"); });
for (const b of document.querySelectorAll("#gears button")) {
  press(b.id || (b.id = "gear-" + b.dataset.gear), () => send({ t: "gear", gear: b.dataset.gear }));
}

if ("DeviceOrientationEvent" in window) {
  window.addEventListener("deviceorientation", (ev) => {
    if (ev.gamma === null || ev.beta === null) return;
    $("tilt-box").hidden = false;
    const angle = (screen.orientation && screen.orientation.angle) || 0;
    const deg = angle === 90 ? ev.beta : angle === 270 || angle === -90 ? -ev.beta
      : angle === 180 ? -ev.gamma : ev.gamma;
    tilt = axis(Math.max(-1, Math.min(1, deg / 35)));
  });
}

// ---------------------------------------------------------------- drawing
// The DOM is touched only where something changed, and the link line at most once a second:
// every change costs the page's thread a layout and a paint, and a touchend waits behind them.
function setText(id, text) {
  const el = $(id);
  if (el.textContent !== text) el.textContent = text;
}
let linkAt = -1e9;  // the first state draws it at once
function note(text, bad) {
  const n = $("note");
  n.textContent = text;
  n.classList.toggle("bad", !!bad);
}

let lastShown = "";
function show(s) {
  try {
    const st = $("status");
    const cls = s.cls + (s.degraded ? " degraded" : "");
    if (st.className !== cls) st.className = cls;
    setText("state", s.state);
    setText("reason", s.reason);
    const key = s.state + "/" + s.reason;
    if (key !== lastShown) {
      lastShown = key;
      estop.shown.push({ state: s.state, reason: s.reason, shown: now() });
    }
  } catch (e) {
    estop.renderErrors++;
  }
}

function drawState(m) {
  let cls = m.state.toLowerCase(), state = m.state, reason = m.reason.replace(/_/g, " ");
  const unit = m.state + (m.reason ? " " + reason : "");
  if (m.error) reason = m.error;
  let hold;
  if (refused) {
    cls = "refused"; state = "NOT PAIRED"; reason = refused; hold = "unit: " + unit;
  } else if (m.hold === "you") {
    hold = m.stalled ? "YOUR HOLD IS STALLED: no fresh frames, nothing sent"
      : m.state === "STOPPED" ? "FINGER DOWN \u00b7 RELEASE to drive"
      : m.state === "ARMED" ? "FINGER DOWN: driving" : "FINGER DOWN";
  } else if (m.hold === "other") {
    hold = "another page holds";
  } else {
    hold = m.state === "STOPPED" ? "no finger \u00b7 one in the middle, then RELEASE"
      : "no finger";
  }
  show({ state, reason, cls, degraded: m.degraded });
  estop.last = m;
  setText("hold", hold);
  drive.classList.toggle("stalled", m.hold === "you" && m.stalled);
  const rtt = pageRtt === null ? "\u2013" : pageRtt.toFixed(0) + " ms";
  const urtt = m.unit_rtt_ms === null ? "\u2013" : m.unit_rtt_ms.toFixed(0) + " ms";
  for (const b of document.querySelectorAll("#gears button")) {
    b.classList.toggle("on", b.dataset.gear === m.gear);
  }
  if (performance.now() - linkAt < 1000) return;
  linkAt = performance.now();
  setText("link", "round trip: page\u21c4remote " + rtt + " \u00b7 remote\u21c4unit " + urtt +
    " \u00b7 packets " + m.sent + " sent, " + m.lost + " lost \u00b7 " + m.late + " frames late");
}

if (!token) refused = "no pairing token: STOP only";
connect();
