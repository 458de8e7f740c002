// busgate fleet dashboard: what the server pushes (/events: a snapshot, then what changed,
// as Server-Sent Events) drawn as a card per gateway and per device, with a minute of its
// joint's value and target (in SI: a position, or a velocity joint's velocity) and current in
// uPlot charts, redrawn RENDER_EVERY_MS. The joint's values come from the server (view.joint,
// made by dashboard/fleet.py), the raw values from the device's state. Each base (two wheels
// as one drive) has a card of its own: its commanded and measured twist and its pose, from its
// latest odometry, and its recent track drawn on a square canvas, the pose marked with its
// heading.
//
// Rules of this file:
// 1. Text from the network goes into the page as text (textContent, never innerHTML).
// 2. Times are the gateways' (wall clock, seconds); "now" is the server's, carried by each
//    message, so an off browser clock moves nothing.
// 3. The only requests are the e-stops, a gateway's reset of its e-stop (once the operator
//    confirms it) and the enables, POSTed as JSON to /api/...
// 4. Drawing is the page's cost: a chart is redrawn only while its card is on screen (and the
//    tab is shown), and only when a sample came or its minute slid by a pixel; a base's track
//    only when an odometry came. Their data is kept up to date whether drawn or not.
"use strict";

const HISTORY_S = 60;
const RENDER_EVERY_MS = 100;
const AGE_EVERY_RENDERS = 5;  // the ages, twice a second: a repaint of every card each time
const EVENTS_SHOWN = 300;
const STATS_STALE_S = 3;
const VALUES = [  // [label, how to read it off a state and its joint's view, as text]
  ["joint", (s, j, name) => named(j, name, j && si(j.value, j.value_unit))],
  ["joint target", (s, j) => j && si(j.target, j.value_unit)],
  ["velocity", (s, j) => j && si(j.velocity, j.velocity_unit)],
  ["effort", (s, j) => j && si(j.effort, j.effort_unit)],
  ["position", (s) => shown(s.position, "")],  // raw, in the device's own units
  ["target", (s) => shown(s.target, "")],
  ["current", (s) => shown(s.current_ma, "mA")],
  ["temperature", (s) => shown(s.temperature_c, "°C")],
  ["force", (s) => shown(s.force_g, "g")],
  ["faults", (s) => (faultsOf(s).length ? faultsOf(s).join(", ") : "none")],
  ["age", null],
];
const BASE_VALUES = [  // [label, how to read it off a base's odometry and measured twist, as text]
  ["commanded linear", (o) => fixed(o.commanded?.linear, 3, "m/s")],
  ["commanded angular", (o) => fixed(o.commanded?.angular, 3, "rad/s")],
  ["measured linear", (o, m) => fixed(m?.linear, 3, "m/s")],  // the gateway's, over 0.1 s
  ["measured angular", (o, m) => fixed(m?.angular, 3, "rad/s")],
  ["x", (o) => fixed(o.x, 3, "m")],
  ["y", (o) => fixed(o.y, 3, "m")],
  ["theta", (o) => fixed(typeof o.theta === "number" ? (o.theta * 180) / Math.PI : null, 1, "°")],
  ["age", null],
];
const TRACK_POINTS = 600;      // as many as dashboard/fleet.py keeps
const TRACK_PX = 200;          // the track's plot: a square, in CSS pixels
const TRACK_MIN_SPAN_M = 1;    // the least it spans: a base at rest is not zoomed into its noise
const GRID_STEPS_M = [0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500, 1000];
const GRID_LINES = 8;          // at most, each way

const gateways = new Map();  // name → {element, buses: tbody, devices: container}
const devices = new Map();   // "gw/dev" → {element, fields, state, t, position, target, current, charts}
const bases = new Map();     // "gw/base" → {element, fields, canvas, odometry, track: [[ts, x, y]]}
let clockOffset = 0;         // server's now − Date.now()/1000
let renders = 0;
const renderMs = [];         // how long the last renders took (the benchmark reads them)
const RENDER_TIMES_KEPT = 600;

const $ = (id) => document.getElementById(id);
const faultsOf = (state) => (Array.isArray(state.faults) ? state.faults.map(String) : []);
const now = () => Date.now() / 1000 + clockOffset;

function fromTemplate(id) {
  return $(id).content.firstElementChild.cloneNode(true);
}

function shown(value, unit) {
  if (value === null || value === undefined) return "—";
  if (typeof value === "number") {
    const text = Number.isInteger(value) ? String(value) : value.toFixed(2);
    return unit ? `${text} ${unit}` : text;
  }
  return String(value);
}

function fixed(value, digits, unit) {  // `digits` decimals, never "-0.000"; "—" for no number
  if (typeof value !== "number") return "—";
  const text = (Number(value.toFixed(digits)) || 0).toFixed(digits);
  return unit === "°" ? `${text}°` : `${text} ${unit}`;
}

function si(value, unit) {  // an SI value: four significant digits (0.0051 m, 1.571 rad/s)
  if (typeof value !== "number") return shown(value, unit);
  const text = String(Number(value.toPrecision(4)));
  return typeof unit === "string" && unit ? `${text} ${unit}` : text;
}

function named(joint, device, text) {  // a joint's name before its value, when not the device's
  if (!joint) return "—";
  return typeof joint.name === "string" && joint.name !== device ? `${joint.name}: ${text}` : text;
}

// -- gateways ------------------------------------------------------------------------------

function gatewayCard(name) {
  let gateway = gateways.get(name);
  if (gateway) return gateway;
  const element = fromTemplate("gateway-template");
  element.dataset.gateway = name;
  element.querySelector(".gateway-name").textContent = name;
  element.querySelector(".estop-gateway").addEventListener("click", () => estop(name));
  element.querySelector(".reset-estop").addEventListener("click", () => resetEstop(name));
  $("gateways").append(element);
  gateway = {element, buses: element.querySelector("tbody"), devices: element.querySelector(".devices"),
             bases: element.querySelector(".bases")};
  gateways.set(name, gateway);
  return gateway;
}

function showGateway(view) {
  const gateway = gatewayCard(view.name);
  gateway.element.querySelector(".gateway-version").textContent = view.version ? `busgate ${view.version}` : "";
  gateway.buses.replaceChildren(...view.buses.map(busRow));
  for (const bus of view.buses) for (const name of bus.devices) deviceCard(view.name, name);
}

function busRow(bus) {
  const stats = bus.stats || {};
  const up = bus.stats !== null && stats.up !== false && now() - (stats.ts || 0) < STATS_STALE_S;
  const row = document.createElement("tr");
  row.dataset.bus = bus.name;
  const cells = [
    bus.name, bus.protocol, up ? "up" : "down",
    stats.utilisation === undefined ? "—" : `${(100 * stats.utilisation).toFixed(1)} %`,
    bus.frames_per_s === undefined || bus.frames_per_s === null ? "—" : bus.frames_per_s.toFixed(0),
    shown(stats.timeouts), shown(stats.checksum_errors), shown(stats.reconnects),
  ];
  for (const [i, text] of cells.entries()) {
    const cell = document.createElement("td");
    cell.textContent = text;
    if (i === 2) cell.className = up ? "up" : "down";
    row.append(cell);
  }
  return row;
}

function forgetGateway(name) {
  const gateway = gateways.get(name);
  if (!gateway) return;
  for (const key of [...devices.keys()]) {
    if (key.startsWith(`${name}/`)) {
      onScreen.unobserve(devices.get(key).element);
      for (const chart of devices.get(key).charts) chart.destroy();
      devices.delete(key);
    }
  }
  for (const key of [...bases.keys()]) {
    if (key.startsWith(`${name}/`)) {
      onScreen.unobserve(bases.get(key).element);
      bases.delete(key);
    }
  }
  gateway.element.remove();
  gateways.delete(name);
}

// -- devices -------------------------------------------------------------------------------

function deviceCard(gatewayName, name) {
  const key = `${gatewayName}/${name}`;
  let device = devices.get(key);
  if (device) return device;
  const element = fromTemplate("device-template");
  element.dataset.device = key;
  element.querySelector(".device-name").textContent = name;
  element.querySelector(".enable").addEventListener("click", () => enable(key));
  const fields = valueList(element.querySelector(".values"), VALUES);
  gatewayCard(gatewayName).devices.append(element);
  device = {element, name, fields, state: null, joint: null, t: [], position: [], target: [],
            current: [], charts: [], visible: false, dirty: true, drawnAt: -Infinity};
  element.busgateCard = device;
  onScreen.observe(element);
  device.charts = [
    chart(element.querySelector(".position-chart"), [["joint", "#2563eb"], ["target", "#f59e0b", [4, 3]]]),
    chart(element.querySelector(".current-chart"), [["current mA", "#dc2626"]]),
  ];
  devices.set(key, device);
  return device;
}

function valueList(list, labels) {  // a <dt> and <dd> per label: the <dd>s by label
  const fields = {};
  for (const [label] of labels) {
    const term = document.createElement("dt");
    term.textContent = label;
    const value = document.createElement("dd");
    value.dataset.field = label;
    value.textContent = "—";
    list.append(term, value);
    fields[label] = value;
  }
  return fields;
}

// Only the cards on screen have their charts redrawn (rule 4): a page of 50 devices costs
// what the dozen in view do.
const onScreen = new IntersectionObserver((entries) => {
  for (const entry of entries) {
    const card = entry.target.busgateCard;
    card.visible = entry.isIntersecting;
    card.dirty ||= card.visible;
  }
});

function chart(where, lines) {
  const series = [{}, ...lines.map(([label, stroke, dash]) => ({label, stroke, dash, width: 1.5, spanGaps: true}))];
  const empty = series.map(() => []);
  return new uPlot({
    width: Math.max(where.clientWidth, 200), height: 110, series, legend: {show: false},
    cursor: {show: false}, scales: {x: {time: true}}, axes: [{size: 24}, {size: 48}],
  }, empty, where);
}

function showDevice(view) {
  const device = deviceCard(view.gateway, view.device);
  device.element.querySelector(".kind").textContent = view.kind;
  if (view.state) device.state = view.state;
  if (view.joint !== undefined) device.joint = view.joint;
  if (view.restart) {  // its gateway's clock was set back, or a browser's first message
    for (const series of ["t", "position", "target", "current"]) device[series] = [];
    device.dirty = true;
  }
  for (const [t, position, target, current] of view.samples) {
    if (device.t.length && t <= device.t[device.t.length - 1]) continue;
    device.t.push(t); device.position.push(position); device.target.push(target); device.current.push(current);
    device.dirty = true;
  }
  const state = device.state;
  if (!state) return;
  const joint = device.joint && typeof device.joint === "object" ? device.joint : null;
  for (const [label, read] of VALUES) {
    if (read) setText(device.fields[label], String(read(state, joint, device.name) ?? "—"));
  }
  device.fields.faults.classList.toggle("faulted", faultsOf(state).length > 0);
  const link = !state.online ? "offline" : state.stale ? "stale" : "online";
  const power = state.estopped ? "e-stopped" : state.enabled === true ? "enabled" : state.enabled === false ? "off" : "unknown";
  setBadge(device.element.querySelector(".link-badge"), link);
  setBadge(device.element.querySelector(".power-badge"), power);
}

// -- bases ---------------------------------------------------------------------------------

function baseCard(gatewayName, name) {
  const key = `${gatewayName}/${name}`;
  let base = bases.get(key);
  if (base) return base;
  const element = fromTemplate("base-template");
  element.dataset.base = key;
  element.querySelector(".base-name").textContent = name;
  const canvas = element.querySelector("canvas.track");
  const ratio = window.devicePixelRatio || 1;
  canvas.width = canvas.height = Math.round(TRACK_PX * ratio);
  canvas.setAttribute("aria-label", `odometry track of base ${name}`);
  const fields = valueList(element.querySelector(".values"), BASE_VALUES);
  gatewayCard(gatewayName).bases.append(element);
  base = {element, name, fields, canvas, ratio, grid: element.querySelector(".grid"), odometry: null,
          measured: null, track: [], visible: false, dirty: true, draws: 0};
  element.busgateCard = base;
  onScreen.observe(element);
  bases.set(key, base);
  return base;
}

function showBase(view) {
  const base = baseCard(view.gateway, view.base);
  if (view.restart) base.track = [];  // its odometry was reset, or a browser's first message
  for (const point of view.track) {
    const last = base.track[base.track.length - 1];
    if (last && point[0] <= last[0]) continue;  // had already (a snapshot, then its drain)
    base.track.push(point);
  }
  if (base.track.length > TRACK_POINTS) base.track.splice(0, base.track.length - TRACK_POINTS);
  if (view.odometry) base.odometry = view.odometry;
  if (view.measured) base.measured = view.measured;
  base.dirty = true;
  const odometry = base.odometry;
  if (!odometry) return;
  for (const [label, read] of BASE_VALUES) {
    if (read) setText(base.fields[label], read(odometry, base.measured));
  }
}

// The track in a square, x to the right and y up (one scale for both), on a grid of a round
// step; the pose a triangle pointing along its heading (theta, counter-clockwise from x).
function drawTrack(base) {
  const context = base.canvas.getContext("2d");
  context.setTransform(base.ratio, 0, 0, base.ratio, 0, 0);
  context.clearRect(0, 0, TRACK_PX, TRACK_PX);
  const odometry = base.odometry || {};
  const pose = typeof odometry.x === "number" && typeof odometry.y === "number" ? [odometry.x, odometry.y] : null;
  const points = base.track.map(([, x, y]) => [x, y]);
  if (pose) points.push(pose);
  const xs = points.map((p) => p[0]);
  const ys = points.map((p) => p[1]);
  const [minX, maxX, minY, maxY] = points.length
    ? [Math.min(...xs), Math.max(...xs), Math.min(...ys), Math.max(...ys)] : [0, 0, 0, 0];
  const span = 1.2 * Math.max(maxX - minX, maxY - minY, TRACK_MIN_SPAN_M);
  const [cx, cy] = [(minX + maxX) / 2, (minY + maxY) / 2];
  const scale = TRACK_PX / span;
  const px = (x) => TRACK_PX / 2 + (x - cx) * scale;
  const py = (y) => TRACK_PX / 2 - (y - cy) * scale;
  const step = GRID_STEPS_M.find((s) => span / s <= GRID_LINES) ?? GRID_STEPS_M[GRID_STEPS_M.length - 1];
  context.lineWidth = 1;
  context.strokeStyle = "#eef0f3";
  context.beginPath();
  for (let i = Math.ceil((cx - span / 2) / step); i * step <= cx + span / 2; i++) {
    const at = Math.round(px(i * step)) + 0.5;
    context.moveTo(at, 0);
    context.lineTo(at, TRACK_PX);
  }
  for (let i = Math.ceil((cy - span / 2) / step); i * step <= cy + span / 2; i++) {
    const at = Math.round(py(i * step)) + 0.5;
    context.moveTo(0, at);
    context.lineTo(TRACK_PX, at);
  }
  context.stroke();
  context.strokeStyle = "#c5cad3";  // the axes, through the odometry's origin
  context.beginPath();
  context.moveTo(Math.round(px(0)) + 0.5, 0);
  context.lineTo(Math.round(px(0)) + 0.5, TRACK_PX);
  context.moveTo(0, Math.round(py(0)) + 0.5);
  context.lineTo(TRACK_PX, Math.round(py(0)) + 0.5);
  context.stroke();
  context.fillStyle = "#6b7280";
  context.font = "10px system-ui, sans-serif";
  if (py(0) > 12 && py(0) < TRACK_PX - 2) context.fillText("x", TRACK_PX - 9, py(0) - 3);
  if (px(0) > 2 && px(0) < TRACK_PX - 12) context.fillText("y", px(0) + 3, 10);
  if (points.length > 1) {
    context.strokeStyle = "#2563eb";
    context.lineWidth = 1.5;
    context.lineJoin = "round";
    context.beginPath();
    for (const [i, [x, y]] of points.entries()) context[i ? "lineTo" : "moveTo"](px(x), py(y));
    context.stroke();
  }
  if (pose) {
    context.fillStyle = "#dc2626";
    context.save();
    context.translate(px(pose[0]), py(pose[1]));
    context.beginPath();
    if (typeof odometry.theta === "number") {
      context.rotate(-odometry.theta);  // the canvas's y is down: counter-clockwise on screen
      context.moveTo(10, 0);
      context.lineTo(-6, 6);
      context.lineTo(-3, 0);
      context.lineTo(-6, -6);
      context.closePath();
    } else {
      context.arc(0, 0, 4, 0, 2 * Math.PI);
    }
    context.fill();
    context.restore();
  }
  setText(base.grid, `(grid ${step} m)`);
  base.dirty = false;
  base.draws++;
}

function setBadge(badge, value) {
  if (badge.dataset.value === value) return;
  badge.textContent = value;
  badge.dataset.value = value;
}

function setText(element, text) {  // an unchanged text is not written: nothing to lay out again
  if (element.textContent !== text) element.textContent = text;
}

// -- the charts, and the ages, every RENDER_EVERY_MS ----------------------------------------

function render() {
  const began = performance.now();
  const end = now();
  const start = end - HISTORY_S;
  for (const device of devices.values()) {
    let drop = 0;
    while (drop < device.t.length && device.t[drop] < start) drop++;
    if (drop) for (const series of [device.t, device.position, device.target, device.current]) series.splice(0, drop);
    if (!device.visible || document.hidden) continue;
    if (device.dirty || end - device.drawnAt >= HISTORY_S / device.charts[0].width) {
      draw(device, start, end);
    }
    const state = device.state;
    if (renders % AGE_EVERY_RENDERS === 0 && state && typeof state.ts === "number") {
      const age = (state.last_reply_age_s ?? 0) + Math.max(0, end - state.ts);
      setText(device.fields.age, shown(age, "s"));
    }
  }
  for (const base of bases.values()) {
    if (!base.visible || document.hidden) continue;
    if (base.dirty) drawTrack(base);
    const odometry = base.odometry;
    if (renders % AGE_EVERY_RENDERS === 0 && odometry && typeof odometry.ts === "number") {
      setText(base.fields.age, shown(Math.max(0, end - odometry.ts), "s"));
    }
  }
  renders++;
  queueMicrotask(() => {  // after uPlot's own microtasks, which draw what setData changed
    renderMs.push(performance.now() - began);
    if (renderMs.length > RENDER_TIMES_KEPT) renderMs.shift();
  });
}

function draw(device, start, end) {
  const last = device.t.length - 1;
  // A state is published when it changes: the last one holds until now.
  const t = last < 0 ? [] : [...device.t, end];
  const hold = (series) => (last < 0 ? [] : [...series, series[last]]);
  const [positions, currents] = device.charts;
  positions.batch(() => {
    positions.setData([t, hold(device.position), hold(device.target)], false);
    positions.setScale("x", {min: start, max: end});
  });
  currents.batch(() => {
    currents.setData([t, hold(device.current)], false);
    currents.setScale("x", {min: start, max: end});
  });
  device.dirty = false;
  device.drawnAt = end;
}

// -- events --------------------------------------------------------------------------------

const shownEvents = new Map();  // an event's text (without its time) → its line

function showEvent({gateway, event}) {
  const {ts, device, type, ...rest} = event;
  const when = typeof ts === "number" ? new Date(ts * 1000).toLocaleTimeString() : "?";
  const pairs = Object.entries(rest).map(([k, v]) => `${k}=${typeof v === "object" ? JSON.stringify(v) : v}`);
  const list = $("events");
  // The same event again (a claim renewed, a device going on and off line) folds into its
  // line, moved to the top with a count, so one chatty device does not push the others away.
  const key = JSON.stringify([gateway, device, type, pairs]);
  let item = shownEvents.get(key);
  if (item) {
    item.busgateCount++;
    item.querySelector(".count").textContent = ` ×${item.busgateCount}`;
  } else {
    item = document.createElement("li");
    item.dataset.type = String(type);  // styled by the stylesheet's known types alone
    item.busgateKey = key;
    item.busgateCount = 1;
    const what = document.createElement("span");
    what.className = "type";
    what.textContent = String(type);
    const details = document.createElement("span");
    details.textContent = pairs.length ? ` ${pairs.join(" ")}` : "";
    const count = document.createElement("span");
    count.className = "count";
    item.append(document.createElement("span"), what, details, count);
    item.firstChild.className = "when";
    shownEvents.set(key, item);
  }
  item.querySelector(".when").textContent = `${when} ${gateway}/${device} `;
  list.prepend(item);
  while (list.children.length > EVENTS_SHOWN) {
    shownEvents.delete(list.lastElementChild.busgateKey);
    list.lastElementChild.remove();
  }
}

// -- what the server pushes ----------------------------------------------------------------

function apply(message, fresh) {
  clockOffset = message.now - Date.now() / 1000;
  if (fresh) {
    for (const name of [...gateways.keys()]) forgetGateway(name);
    $("events").replaceChildren();
    shownEvents.clear();
  }
  for (const name of message.gone || []) forgetGateway(name);
  // One malformed view (a hostile or broken gateway's) is left out, never the rest.
  for (const view of message.gateways) guarded(showGateway, view);
  for (const view of message.devices) guarded(showDevice, view);
  for (const view of message.bases || []) guarded(showBase, view);
  for (const entry of message.events) guarded(showEvent, entry);
  $("empty").hidden = gateways.size > 0;
  const counted = [`${gateways.size} gateways`, `${devices.size} devices`, ...(bases.size ? [`${bases.size} bases`] : [])];
  setText($("counts"), counted.join(" · "));
}

let leftOut = 0;  // views that could not be shown (the tests read it)

function guarded(show, view) {
  try {
    show(view);
  } catch {
    leftOut++;
  }
}

function connect() {
  const source = new EventSource("/events");
  source.addEventListener("snapshot", (e) => { apply(JSON.parse(e.data), true); setLink("live"); });
  source.addEventListener("delta", (e) => apply(JSON.parse(e.data), false));
  source.addEventListener("error", () => setLink("connecting"));
}

function setLink(state) {
  $("link").dataset.state = state;
  $("link").textContent = state === "live" ? "live" : "reconnecting…";
}

// -- the three actions ---------------------------------------------------------------------

async function post(path, body, what) {
  try {
    const response = await fetch(path, {method: "POST", headers: {"Content-Type": "application/json"},
                                        body: JSON.stringify(body)});
    const reply = await response.json();
    notice(reply.ok ? `${what}: sent` : `${what}: ${reply.error.code}: ${reply.error.message}`);
  } catch (error) {
    notice(`${what}: ${error}`);
  }
}

function notice(text) {
  const line = $("notice");
  line.textContent = text;
  line.hidden = false;
}

const estop = (gateway) => post("/api/estop", {gateway}, gateway ? `e-stop ${gateway}` : "fleet e-stop");
const enable = (device) => post("/api/enable", {device}, `enable ${device}`);

function resetEstop(gateway) {
  const asked = `Reset the e-stop of gateway ${gateway}? Each device goes back to the power state `
    + "it had before the stop and holds still; nothing moves until a new command. A device a "
    + "client claims stays e-stopped for that client to reset.";
  if (confirm(asked)) post("/api/reset_estop", {gateway}, `reset ${gateway}`);
}

$("estop-fleet").addEventListener("click", () => estop(null));
window.busgateDashboard = {  // for the browser tests and the benchmark
  series: (key) => { const d = devices.get(key); return d && {t: d.t, position: d.position, target: d.target, current: d.current}; },
  base: (key) => { const b = bases.get(key); return b && {odometry: b.odometry, measured: b.measured, track: b.track, draws: b.draws}; },
  renders: () => renders,
  renderMs: () => [...renderMs],
  leftOut: () => leftOut,
};
connect();
setInterval(render, RENDER_EVERY_MS);
