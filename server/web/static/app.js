// The operator page's behaviour: log in/out, the Live page's server-sent events, actions with
// confirmation, and the SPC and calibration charts (uPlot). No framework; htmx handles the History filters.
"use strict";

// The page's language: its messages (server/web/jstext.py, translated from the page's one
// catalogue), its BCP 47 tag and the plant's time zone, in the JSON block the server wrote.
const I18N = (() => {
  const el = document.getElementById("i18n");
  try { return el ? JSON.parse(el.textContent) : {}; } catch (e) { return {}; }
})();
const LANG = I18N.lang || "en";

// A message in the page's language, its {names} filled from `args`.
function t(message, args) {
  const text = (I18N.messages && I18N.messages[message]) || message;
  return text.replace(/\{(\w+)\}/g, (m, k) => (args && k in args ? String(args[k]) : m));
}

const NUMBER_FORMATS = {};
// A number with `digits` decimals in the page's locale (decimal comma in German and Spanish).
function localNumber(v, digits) {
  const key = String(digits);
  const f = NUMBER_FORMATS[key] || (NUMBER_FORMATS[key] = new Intl.NumberFormat(LANG,
    {minimumFractionDigits: digits, maximumFractionDigits: digits, useGrouping: false}));
  return f.format(v);
}

// The user's language: a cookie for a year, then the page again in it.
function setupLanguage() {
  const sel = document.getElementById("lang-select");
  if (!sel) return;
  sel.addEventListener("change", () => {
    document.cookie = sel.dataset.cookie + "=" + encodeURIComponent(sel.value) +
      "; path=/; max-age=31536000; SameSite=Lax";
    window.location.reload();
  });
}

function postJSON(url, body) {
  return fetch(url, {method: "POST", credentials: "same-origin",
    headers: {"Content-Type": "application/json", "Accept": "application/json"},
    body: JSON.stringify(body || {})}).then(async (r) => {
    const data = await r.json().catch(() => ({}));
    if (!r.ok) throw new Error(data.detail || data.title || ("HTTP " + r.status));
    return data;
  });
}

function say(el, text, ok) {
  const msg = el && (el.closest("details, section, dialog")?.querySelector(".msg") || document.querySelector(".msg"));
  if (!msg) return;
  msg.textContent = text;
  msg.className = "msg " + (ok ? "done" : "error");
}

// A user's name and PIN or password (#login-form), or an API token (#token-form).
function setupLogin() {
  const forms = {"login-form": (f) => ({user: f.user.value.trim(), secret: f.secret.value}),
                 "token-form": (f) => ({token: f.token.value})};
  Object.entries(forms).forEach(([id, body]) => {
    const form = document.getElementById(id);
    if (!form) return;
    form.addEventListener("submit", (ev) => {
      ev.preventDefault();
      postJSON("/web/login", body(form))
        .then(() => { window.location.assign(form.dataset.next || "/"); })
        .catch((err) => say(form, err.message, false));
    });
  });
}

function setupLogout() {
  const btn = document.getElementById("logout");
  if (btn) btn.addEventListener("click", () =>
    postJSON("/web/logout").finally(() => window.location.assign("/login")));
}

function setupActions() {
  document.querySelectorAll("button.post").forEach((btn) => btn.addEventListener("click", () => {
    if (btn.dataset.confirm && !window.confirm(btn.dataset.confirm)) return;
    btn.disabled = true;
    postJSON(btn.dataset.action, btn.dataset.body ? JSON.parse(btn.dataset.body) : {})
      .then((data) => {
        say(btn, data.message || (data.acked_by ? "acknowledged by " + data.acked_by : t("done")), data.passed !== false);
        if (btn.dataset.action.endsWith("/activate")) setTimeout(() => window.location.reload(), 800);
        if (btn.dataset.reload) window.location.reload();
      })
      .catch((err) => say(btn, err.message, false))
      .finally(() => { btn.disabled = false; });
  }));
  const trig = document.getElementById("trigger-form");
  if (trig) trig.addEventListener("submit", (ev) => {
    ev.preventDefault();
    postJSON(trig.dataset.action, {part_id: trig.part_id.value || null})
      .then((d) => say(trig, d.message + (d.measurement_id ? " (" + t("record #{id}", {id: d.measurement_id}) + ")" : ""),
                       d.result_code === 0))
      .catch((err) => say(trig, err.message, false));
  });
  const open = document.getElementById("teach-open");
  const dialog = document.getElementById("teach-dialog");
  if (open && dialog) open.addEventListener("click", () => dialog.showModal());
}

// The station's actions follow the station: a Live page left open greys them out when the
// status panel (pushed every second) says the station is down, and offers them again when it
// is back.
function stationActions() {
  const state = document.querySelector("#status .state");
  if (!state) return;
  const down = state.dataset.state === "DOWN";
  document.querySelectorAll("[data-needs-station]").forEach((b) => {
    b.disabled = down;
    if (down) b.title = t("station down"); else b.removeAttribute("title");
  });
}

// A filter the server refuses (400) comes with the page's words for it: show them (htmx swaps
// only 2xx answers unless told).
function setupHtmxErrors() {
  document.body.addEventListener("htmx:beforeSwap", (ev) => {
    if (ev.detail.xhr && ev.detail.xhr.status === 400) {
      ev.detail.shouldSwap = true;
      ev.detail.isError = false;
    }
  });
}

function setupLive() {
  const live = document.getElementById("live");
  if (!live || !window.EventSource) return;
  const events = new EventSource(live.dataset.events);
  const swap = (ev) => {
    const tpl = document.createElement("template");
    tpl.innerHTML = ev.data.trim();
    const fresh = tpl.content.firstElementChild;
    const old = fresh && document.getElementById(fresh.id);
    if (old) old.replaceWith(fresh);
    if (ev.type === "status") stationActions();
    live.dataset.updates = String(Number(live.dataset.updates || 0) + 1);
  };
  ["result", "frames", "status"].forEach((name) => events.addEventListener(name, swap));
  events.addEventListener("open", () => { live.dataset.connected = "1"; });
}

// ------------------------------------------------------------------------- live camera view
function setupCameraView() {
  const view = document.getElementById("camera-view");
  if (!view || !window.EventSource) return;
  const grid = document.getElementById("camera-grid");
  const note = document.getElementById("camera-note");
  const peaks = {};  // the highest focus figure of each camera while the page is open
  const events = new EventSource(view.dataset.events);
  const figure = (cid) => {
    let fig = grid.querySelector(`figure[data-camera="${CSS.escape(cid)}"]`);
    if (fig) return fig;
    fig = document.createElement("figure");
    fig.dataset.camera = cid;
    fig.innerHTML = '<img alt=""><figcaption><h2></h2><p class="focus"></p>' +
      '<meter min="0" max="1" value="0"></meter><dl></dl><p class="note"></p></figcaption>';
    fig.querySelector("h2").textContent = t("Camera {camera}", {camera: cid});
    fig.querySelector("img").alt = t("camera {camera}, newest frame", {camera: cid});
    fig.querySelector("meter").setAttribute("aria-label", t("focus of camera {camera} against its peak", {camera: cid}));
    grid.appendChild(fig);
    return fig;
  };
  events.addEventListener("frames", (ev) => {
    const d = JSON.parse(ev.data);
    d.cameras.forEach((c) => {
      const fig = figure(c.camera_id);
      const img = fig.querySelector("img");
      if (c.src) { img.src = c.src; img.width = c.width; img.height = c.height; }
      if (c.focus !== null) peaks[c.camera_id] = Math.max(peaks[c.camera_id] || 0, c.focus);
      const peak = peaks[c.camera_id];
      fig.dataset.focus = c.focus === null ? "" : String(c.focus);
      fig.querySelector(".focus").textContent = peak
        ? t("Focus {focus} (peak {peak})", {focus: fmt(c.focus, 1), peak: fmt(peak, 1)})
        : t("Focus {focus}", {focus: fmt(c.focus, 1)});
      const meter = fig.querySelector("meter");
      meter.value = peak && c.focus !== null ? c.focus / peak : 0;
      const dl = fig.querySelector("dl");
      dl.replaceChildren();
      [[t("focus over"), c.focus_area ? t(c.focus_area) : "—"], [t("mean grey"), fmt(c.mean, 1)],
       [t("saturated"), fmt(c.saturated_pct, 2) + " %"], [t("dark"), fmt(c.dark_pct, 2) + " %"],
       [t("taken"), c.grabbed_at ? new Date(c.grabbed_at).toLocaleTimeString(I18N.lang || undefined, {timeZone: I18N.zone || undefined}) : "—"]]
        .forEach(([k, v]) => {
          const dt = document.createElement("dt"); dt.textContent = k;
          const dd = document.createElement("dd"); dd.textContent = v;
          dl.append(dt, dd);
        });
      fig.querySelector(".note").textContent = c.note;
    });
    note.textContent = d.note || t("Frame set {seq}, at most one every {period} s.", {seq: d.seq, period: fmt(d.period_s, 1)});
    note.classList.toggle("error", false);
    view.dataset.seq = String(d.seq);
    view.dataset.updates = String(Number(view.dataset.updates || 0) + 1);
  });
  events.addEventListener("down", (ev) => {
    note.textContent = t("No frames: {why}", {why: ev.data});
    note.classList.toggle("error", true);
  });
  events.addEventListener("open", () => { view.dataset.connected = "1"; });
}

// ------------------------------------------------------------------------------------ charts
const COLORS = ["#1d4ed8", "#b91c1c", "#15803d", "#a16207", "#7c3aed", "#0e7490", "#be185d", "#4b5563"];

function chart(host, title, x, series, opts) {
  opts = opts || {};
  const box = document.createElement("div");
  box.className = "chart";
  box.innerHTML = "<h3></h3>";
  host.appendChild(box);
  const data = [x];
  const spec = [{label: t("Time")}];
  const values = [];
  series.forEach((s, i) => {
    data.push(s.values);
    if (s.marks) {  // points that break a run rule: drawn as dots, no line
      spec.push({label: s.label, stroke: "#b91c1c", fill: "#b91c1c", paths: () => null,
        points: {show: true, size: 9, stroke: "#b91c1c", fill: "#b91c1c"}});
      return;
    }
    spec.push({label: s.label, stroke: s.color || (s.band ? "#6b7280" : COLORS[i % COLORS.length]),
      dash: s.dash || (s.band ? [6, 4] : undefined), width: 1.5,
      points: {show: !s.band && x.length < 200}, spanGaps: false});
    if (!s.band) s.values.forEach((v) => { if (v !== null && v !== undefined) values.push(v); });
  });
  let lo = Math.min(...values), hi = Math.max(...values);
  if (!isFinite(lo)) { lo = opts.log ? 0.01 : -1; hi = 1; }
  // Tolerances: on a log scale every band fits next to the data; on a linear one a band far
  // outside the data would flatten it, so it is named in the title instead.
  const off = [];
  series.filter((s) => s.band).forEach((s) => {
    const v = s.values.find((y) => y !== null && y !== undefined);
    if (v === undefined) return;
    if (opts.log || Math.abs(v) <= 20 * Math.max(Math.abs(lo), Math.abs(hi), 1e-9)) {
      lo = Math.min(lo, v); hi = Math.max(hi, v);
    } else off.push(s.label + " " + localNumber(v, 3));
  });
  box.querySelector("h3").textContent = title + (off.length ? " — " + t("off the scale: {bands}", {bands: off.join(", ")}) : "");
  let range;
  if (opts.log) {
    lo = Math.max(lo, 1e-6);
    const r = uPlot.rangeLog(lo, hi, 10, true);  // whole decades: uPlot's log axis needs them
    range = () => r;
  } else {
    // A flat series (one point, or every value equal) still gets a span its ticks can tell
    // apart: a tenth of its size, at least 1 unit.
    const mag = Math.max(Math.abs(lo), Math.abs(hi));
    const pad = hi - lo > 1e-6 * Math.max(mag, 1) ? 0.08 * (hi - lo) : Math.max(0.1 * mag, 1);
    range = () => [lo - pad, hi + pad];
  }
  const width = Math.max(Math.min(host.clientWidth - 10, 1400), 320);
  const plot = new uPlot({width: width, height: opts.height || 220, series: spec,
    tzDate: (ts) => uPlot.tzDate(new Date(ts * 1e3), ZONE),  // ticks on the plant's hours
    scales: {x: {time: true, range: timeRange(x)}, y: {distr: opts.log ? 3 : 1, log: 10, range: range}},
    axes: [{values: timeTicks, label: t("time ({zone})", {zone: ZONE})},
           // 24 px between y ticks (uPlot's 30 leaves one tick on a short chart's narrow range)
           {label: opts.unit || "", space: 24, values: opts.log ? undefined : numberTicks}],
    cursor: {drag: {x: true, y: false}}}, data, box);
  box.plot = plot;  // the browser tests read the drawn tick labels (plot.axes[i]._values)
  return plot;
}

// The time axis spans the points; one point (or several at one instant) gets a minute
// (uPlot would give a lone point 86,400 of its units: 1000 days when they are seconds).
function timeRange(x) {
  const lo = x.length ? x[0] : null, hi = x.length ? x[x.length - 1] : null;
  return (u, min, max) => {
    if (min === null || max === null) return [0, 60];
    if (lo !== null && hi - lo < 1 && min === lo) return [lo - 30, hi + 30];
    return max - min < 1 ? [min - 30, max + 30] : [min, max];
  };
}

// The plant's time zone (the station file's time_zone, an IANA name): every time on the
// charts is the plant's wall-clock time.
let ZONE = I18N.zone || "UTC";
const ZONE_FORMATS = {};

// 2026-11-02T07:00:00.000 in ZONE (the layout of toISOString, without the Z).
function zoneTime(t) {
  const ms = Math.round(t * 1000);
  let f = ZONE_FORMATS[ZONE];
  if (!f) {
    f = ZONE_FORMATS[ZONE] = new Intl.DateTimeFormat("en-CA", {timeZone: ZONE, hourCycle: "h23",
      year: "numeric", month: "2-digit", day: "2-digit", hour: "2-digit", minute: "2-digit",
      second: "2-digit"});
  }
  const p = {};
  f.formatToParts(new Date(ms)).forEach((x) => { p[x.type] = x.value; });
  return p.year + "-" + p.month + "-" + p.day + "T" + p.hour + ":" + p.minute + ":" + p.second +
    "." + String(((ms % 1000) + 1000) % 1000).padStart(3, "0");
}

const DATE_FORMATS = {};
// The date of `t` in the plant's zone, in the page's locale (`opts`: Intl's date fields).
function zoneDate(t, opts) {
  const key = ZONE + JSON.stringify(opts);
  const f = DATE_FORMATS[key] || (DATE_FORMATS[key] = new Intl.DateTimeFormat(LANG,
    Object.assign({timeZone: ZONE}, opts)));
  return f.format(new Date(Math.round(t * 1000)));
}

// A moment in the plant's time, the locale's date and 24-hour time, and the zone.
function stamp(t) {
  return zoneDate(t, {year: "numeric", month: "short", day: "numeric", hour: "2-digit",
    minute: "2-digit", second: "2-digit", hourCycle: "h23"}) + " " + ZONE;
}

// Time ticks in the plant's zone, as precise as the tick step needs and with the date (in the
// page's locale) once the span passes most of a day (uPlot's own labels read ":53.900" on
// short spans).
function timeTicks(u, splits, axisIdx, space, incr) {
  const span = u.scales.x.max - u.scales.x.min;
  const d = incr < 1 ? Math.min(3, Math.ceil(-Math.log10(incr) - 1e-9)) : 0;
  const point = localNumber(0.5, 1).charAt(1);
  return splits.map((x) => {
    const s = zoneTime(x);  // 2026-11-02T07:00:00.000
    if (incr >= 86400) return zoneDate(x, {year: "numeric", month: "2-digit", day: "2-digit"});
    if (span > 20 * 3600) return zoneDate(x, {month: "2-digit", day: "2-digit"}) + " " + s.slice(11, 16);
    if (incr >= 60) return s.slice(11, 16);
    return s.slice(11, 19) + (d ? point + s.slice(20, 20 + d) : "");
  });
}

// Number ticks with the decimals the tick step needs: no two equal labels, never "−0".
function numberTicks(u, splits, axisIdx, space, incr) {
  const d = Math.max(0, Math.min(9, Math.ceil(-Math.log10(incr) - 1e-9)));
  return splits.map((v) => {
    const s = v.toFixed(d);
    const shown = /^-0(\.0*)?$/.test(s) ? s.slice(1) : s;
    return localNumber(Number(shown), d).replace(/^[-\u2212]/, "\u2212");
  });
}

function band(n, value) { return new Array(n).fill(value === undefined ? null : value); }

function para(host, cls, text) {
  const p = document.createElement("p");
  p.className = cls;
  p.textContent = text;
  host.appendChild(p);
  return p;
}

function fmt(v, digits) { return v === null || v === undefined ? "—" : localNumber(Number(v), digits); }

// One I-MR chart per offset axis and camera residual (server/web/spc.py computes everything:
// limits from the baseline, the run rules' points, Cp/Cpk and Pp/Ppk).
function drawSpc(host, d) {
  const head = {n: d.points, recipe: d.recipe, baseline: d.baseline, zone: d.time_zone};
  para(host, "spc-head", d.recipe
    ? t("{n} results, tolerances of {recipe}; control limits from {baseline}; times in {zone}.", head)
    : t("{n} results; control limits from {baseline}; times in {zone}.", head));
  d.charts.forEach((c) => {
    const box = document.createElement("section");
    box.className = "spc";
    box.dataset.key = c.key;
    host.appendChild(box);
    if (!c.points) { para(box, "muted", c.title + ": " + (c.message || t("no values"))); return; }
    const n = c.t.length, L = c.limits, name = c.key.split(".").pop();
    const ind = [{label: name, values: c.values}];
    if (L) {
      ind.push({label: t("UCL"), band: true, color: "#b91c1c", dash: [3, 3], values: band(n, L.ucl)},
               {label: t("centre"), band: true, color: "#15803d", dash: [1, 0], values: band(n, L.center)},
               {label: t("LCL"), band: true, color: "#b91c1c", dash: [3, 3], values: band(n, L.lcl)});
    }
    if (c.usl !== null) ind.push({label: t("USL (tolerance)"), band: true, values: band(n, c.usl)});
    if (c.lsl !== null) ind.push({label: t("LSL (tolerance)"), band: true, values: band(n, c.lsl)});
    ind.push({label: t("run rule broken"), marks: true, values: c.flagged});
    chart(box, t("{title}: individuals", {title: c.title}), c.t, ind, {unit: c.unit, height: 230});
    const mr = [{label: t("moving range"), values: c.mr}];
    if (L) {
      mr.push({label: t("UCL"), band: true, color: "#b91c1c", dash: [3, 3], values: band(n, L.mr_ucl)},
              {label: "MR\u0304", band: true, color: "#15803d", dash: [1, 0], values: band(n, L.mr_center)});
    }
    chart(box, t("{title}: moving range", {title: c.title}), c.t, mr, {unit: c.unit, height: 200});
    if (c.message) para(box, "hook", c.message);
    const k = c.capability;
    para(box, "capability", k ? t("Over the {n} points: Cp {cp}, Cpk {cpk} (σ within {sw} {unit}); " +
      "Pp {pp}, Ppk {ppk} (σ overall {so} {unit}).", {n: k.n, cp: fmt(k.cp, 2), cpk: fmt(k.cpk, 2),
      sw: fmt(k.sigma_within, 4), unit: c.unit, pp: fmt(k.pp, 2), ppk: fmt(k.ppk, 2),
      so: fmt(k.sigma_overall, 4)}) : t("No tolerance for this series: no capability."));
    const ul = document.createElement("ul");
    ul.className = "rules";
    c.rules.forEach((r) => {
      const li = document.createElement("li");
      li.className = "rule-broken";
      li.dataset.rule = String(r.rule);
      li.textContent = t("Rule {n}", {n: r.rule}) + (r.western_electric ? " (" + t("Western Electric") + ")" : "") + ", " +
        r.name + ": " + (r.count === 1 ? t("1 point") : t("{n} points", {n: r.count})) +
        (r.count > r.points.length ? " (" + t("the newest {n}", {n: r.points.length}) + ")" : "") + " — " +
        r.points.map((p) => zoneTime(p.t).replace("T", " ").slice(0, 19) + " #" + p.id + " " +
          fmt(p.value, 3)).join("; ");
      ul.appendChild(li);
    });
    if (!c.rules.length) {
      const li = document.createElement("li");
      li.textContent = L ? t("No run rule broken.") : t("No control limits: no run rules.");
      ul.appendChild(li);
    }
    box.appendChild(ul);
  });
}

function drawCalibration(host, d) {
  const c = d.columns, n = c.t.length;
  c.cameras.forEach((cam) => chart(host, t("Camera {camera}: mean residual (px)", {camera: cam}), c.t, [
    {label: "du", values: c.camera_du[cam]}, {label: "dv", values: c.camera_dv[cam]},
    {label: "RMS", values: c.camera_rms[cam]}, {label: "0", band: true, values: band(n, 0)}], {unit: "px", height: 180}));
}

function setupCharts() {
  const host = document.getElementById("charts");
  if (!host) return;
  ZONE = host.dataset.tz || "UTC";
  const form = document.getElementById("trend-filters");
  let asked = 0;  // a slower earlier answer must not replace the newest one's charts
  const load = () => {
    const mine = ++asked;
    const q = new URLSearchParams();
    new FormData(form).forEach((v, k) => { if (v) q.set(k, v); });
    host.textContent = t("loading…");
    delete host.dataset.points;
    const t0 = performance.now();
    fetch(host.dataset.src + "?" + q.toString(), {credentials: "same-origin"})
      .then(async (r) => {
        const d = await r.json();
        if (!r.ok) throw new Error(d.detail || ("HTTP " + r.status));
        return d;
      }).then((d) => {
        if (mine !== asked) return;
        host.textContent = "";
        const t1 = performance.now();
        ZONE = d.time_zone || host.dataset.tz || "UTC";
        (host.dataset.kind === "calibration" ? drawCalibration : drawSpc)(host, d);
        host.dataset.renderMs = String(Math.round(performance.now() - t1));
        host.dataset.loadMs = String(Math.round(t1 - t0));
        host.dataset.points = String(d.columns ? d.columns.t.length : d.points);
        host.dataset.limit = q.get("limit") || "";
      }).catch((err) => { if (mine === asked) host.textContent = t("could not load: {error}", {error: err.message}); });
  };
  form.addEventListener("submit", (ev) => { ev.preventDefault(); load(); });
  load();
}

function cell(row, text, cls) {
  const td = document.createElement("td");
  td.textContent = text === null || text === undefined ? "—" : String(text);
  if (cls) td.className = cls;
  row.appendChild(td);
}

// The drift engineer's report (GET /api/v1/drift, server/drift.py DriftReport): overall status,
// one line per camera in warning or alarm, and each camera's state.
function setupDrift() {
  const box = document.getElementById("drift");
  if (!box || !box.dataset.src) return;
  fetch(box.dataset.src, {credentials: "same-origin"}).then(async (r) => {
    const d = await r.json();
    if (!r.ok) throw new Error(d.detail || ("HTTP " + r.status));
    box.textContent = "";
    const head = document.createElement("p");
    head.className = "drift-status " + d.status;
    head.dataset.status = d.status;
    head.textContent = t("Drift watch: {status} — {records} records of {recipe} with calibration " +
      "{calibration}.", {status: t(d.status), records: d.records, recipe: d.recipe || "—",
      calibration: d.calibration_id || t("of the station file")});
    box.appendChild(head);
    const ul = document.createElement("ul");
    [...new Set(d.messages || [])].forEach((m) => {
      const li = document.createElement("li");
      li.className = "drift-warning";
      li.textContent = m;
      ul.appendChild(li);
    });
    if (!ul.children.length) {
      const li = document.createElement("li");
      li.textContent = t("No camera in warning or alarm.");
      ul.appendChild(li);
    }
    box.appendChild(ul);
    const table = document.createElement("table");
    const heads = document.createElement("tr");
    ["camera", "status", "what", "move px", "since", "triggers"].forEach((h) => {
      const th = document.createElement("th");
      th.textContent = t(h);
      heads.appendChild(th);
    });
    table.appendChild(heads);
    (d.cameras || []).forEach((c) => {
      const tr = document.createElement("tr");
      cell(tr, (c.view > 1 ? "v" + c.view + "/" : "") + c.camera_id);
      cell(tr, t(c.status), c.status === "alarm" || c.status === "warning" ? "drift-warning" : "");
      cell(tr, c.message);
      cell(tr, c.shift_px === null || c.shift_px === undefined ? null : localNumber(c.shift_px, 2));
      cell(tr, c.since ? stamp(Date.parse(c.since) / 1000) : null);
      cell(tr, c.learning_left ? t("{n} (learning: {left} to go)", {n: c.triggers, left: c.learning_left}) : c.triggers);
      table.appendChild(tr);
    });
    box.appendChild(table);
    const v = d.last_verify;
    const verify = document.createElement("p");
    verify.className = "drift-verify";
    if (v) {
      const a = document.createElement("a");
      a.href = "/history/" + v.measurement_id;
      a.textContent = t("record #{id}", {id: v.measurement_id});
      const [before, after] = t("Last verify ({when}, {record}): {message}", {
        when: stamp(Date.parse(v.triggered_at) / 1000), message: v.message}).split("{record}");
      verify.append(before, a, after === undefined ? "" : after);
      if (v.passed === false) verify.classList.add("drift-warning");
    } else {
      verify.textContent = t("No calibration verify recorded yet.");
    }
    box.appendChild(verify);
    delete box.dataset.loading;
  }).catch((err) => {
    box.textContent = t("drift watch: {error}", {error: err.message});
    delete box.dataset.loading;
  });
}

document.addEventListener("DOMContentLoaded", () => {
  setupLanguage(); setupLogin(); setupLogout(); setupActions(); setupHtmxErrors(); setupLive(); setupCharts();
  setupDrift(); setupCameraView();
});
