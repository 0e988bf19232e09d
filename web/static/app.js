// imunoise dashboard: reads the HTTP API, redraws on server-sent "update" events.
"use strict";

const params = new URLSearchParams(location.search);
const token = params.get("token");
// changes counts the starts and ends of model changes made from this page: a refresh that
// overlaps one may hold a diagnosis asked for before it and a model after it, and is not drawn
const state = { channel: params.get("channel"), plots: {}, busy: false, pending: false,
                lastRefresh: 0, renders: 0, changes: 0 };
const COLORS = ["#d62728", "#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#17becf", "#bcbd22",
                "#ff7f0e"];
const $ = (id) => document.getElementById(id);

function fmt(v, digits = 3) {
  if (v === null || v === undefined || !isFinite(v)) return "–";
  if (v === 0) return "0";
  const a = Math.abs(v);
  return (a >= 1e4 || a < 1e-3) ? v.toExponential(digits - 1) : v.toPrecision(digits);
}

async function getJSON(path) {
  const r = await fetch(path, { cache: "no-store" });
  if (!r.ok) throw new Error(`${path}: ${r.status} ${(await r.json()).detail || ""}`);
  return r.json();
}

function plot(id, opts, data) {
  const el = $(id);
  if (state.plots[id]) state.plots[id].destroy();
  el.textContent = "";
  opts.width = Math.max(el.clientWidth || 400, 300);
  opts.height = opts.height || 300;
  state.plots[id] = new uPlot(opts, data, el);
  el.dataset.points = String(data[0].length);
}

// Log scales span whole decades around the finite positive data (uPlot's automatic log range
// misbehaves on spans of less than about two decades).
function decades(u, min, max) {
  if (!(min > 0) || !(max > 0)) return [1e-12, 1];
  let lo = Math.floor(Math.log10(min));
  let hi = Math.ceil(Math.log10(max));
  if (hi <= lo) hi = lo + 1;
  return [10 ** lo, 10 ** hi];
}
const LOG = { distr: 3, range: decades };

// Log axes label the decades only, as Stable32 and matplotlib do: 10⁻³, 10⁻², 1, 10 ...
// uPlot hands the minor ticks in too (null where its own filter dropped them); they stay bare.
const SUPERSCRIPT = { "-": "⁻", 0: "⁰", 1: "¹", 2: "²", 3: "³", 4: "⁴", 5: "⁵", 6: "⁶", 7: "⁷",
                      8: "⁸", 9: "⁹" };

function decadeLabel(v) {
  if (!(v > 0)) return "";
  const e = Math.log10(v);
  const n = Math.round(e);
  if (Math.abs(e - n) > 1e-9) return "";
  if (n === 0) return "1";
  if (n === 1) return "10";
  return "10" + String(n).split("").map((c) => SUPERSCRIPT[c]).join("");
}

function logAxis(label) {
  return { label, values: (u, vals) => vals.map(decadeLabel) };
}

function drawAllan(a) {
  $("allan-units").textContent = `(${a.units})`;
  const series = [{ label: "tau (s)" },
    { label: "measured", stroke: "#1f77b4", width: 2, points: { show: true, size: 5 } },
    { label: "95 % high", stroke: "#1f77b455", width: 1 },
    { label: "95 % low", stroke: "#1f77b455", width: 1 }];
  const data = [a.tau_s, a.adev, a.ci_high, a.ci_low];
  if (a.model_adev) {
    series.push({ label: "model", stroke: "#000", width: 2 });
    data.push(a.model_adev);
    // A term the data do not need sits near zero: draw only where it is within two decades
    // of the measurement, so the log axis keeps to the data.
    const floor = 1e-2 * Math.min(...a.adev.filter((v) => v > 0));
    Object.entries(a.terms).forEach(([name, ys], i) => {
      series.push({ label: name, stroke: COLORS[i % COLORS.length], width: 1, dash: [6, 4] });
      data.push(ys.map((v) => (v > floor ? v : null)));
    });
  }
  plot("allan-plot", {
    scales: { x: LOG, y: LOG },
    series, bands: [{ series: [2, 3], fill: "#1f77b422" }],
    axes: [logAxis("averaging time tau (s)"), logAxis(`Allan deviation (${a.units})`)],
  }, data);

  const z = a.z || a.tau_s.map(() => null);
  const bad = z.map((v) => (v !== null && Math.abs(v) > 3 ? v : null));
  plot("z-plot", {
    height: 140,
    scales: { x: LOG },
    series: [{ label: "tau (s)" },
      { label: "z", stroke: "#1f77b4", paths: () => null, points: { show: true, size: 6 } },
      { label: "failure", stroke: "#d00", fill: "#d00", paths: () => null,
        points: { show: true, size: 9, fill: "#d00" } },
      { label: "+3", stroke: "#999", dash: [4, 4] }, { label: "−3", stroke: "#999", dash: [4, 4] }],
    axes: [logAxis("tau (s)"), { label: "z" }],
  }, [a.tau_s, z, bad, a.tau_s.map(() => 3), a.tau_s.map(() => -3)]);
  $("z-plot").dataset.failures = String(bad.filter((v) => v !== null).length);
  $("failures").innerHTML = a.failures.map((f) =>
    `<li>${f.direction} for tau ${fmt(f.tau_s[0])}–${fmt(f.tau_s[1])} s (max |z| ${fmt(f.max_abs_z)})</li>`
  ).join("");
}

function drawPsd(p) {
  $("psd-units").textContent = `(${p.units})`;
  if (!p.f_hz.length) { $("psd-plot").textContent = "waiting for a full PSD segment…"; return; }
  const series = [{ label: "f (Hz)" }, { label: "PSD", stroke: "#1f77b4", width: 1 },
    { label: "95 % high", stroke: "#1f77b433" }, { label: "95 % low", stroke: "#1f77b433" }];
  const pos = (ys) => ys.map((v) => (v > 0 ? v : null));
  const data = [p.f_hz, pos(p.psd), pos(p.ci_high), pos(p.ci_low)];
  if (p.model_psd) {
    series.push({ label: "model", stroke: "#000", width: 2 });
    data.push(p.model_psd.map((v) => (v > 0 ? v : null)));
  }
  plot("psd-plot", { scales: { x: LOG, y: LOG }, series,
    bands: [{ series: [2, 3], fill: "#1f77b422" }],
    axes: [logAxis("frequency (Hz)"), logAxis(p.units)] }, data);
}

// Coherence between the stream's channels: every pair on log-frequency axes with the
// zero-coherence threshold (family-wise 5 %), and the matrix of each pair's highest value.
function drawCoherence(c) {
  const info = $("coherence-info");
  if (!c || !c.ready) {
    info.textContent = `waiting: ${(c && c.reason) || "no data yet"}`;
    return;
  }
  info.textContent = `${c.stream}: ${c.n_segments} segments of ${c.nperseg} samples; ` +
    "exact 95 % intervals in the data; dashed: the zero-coherence threshold (5 %, whole axis)";
  const series = [{ label: "f (Hz)" }];
  const data = [c.f_hz];
  c.pairs.forEach(([a, b], i) => {
    series.push({ label: `${a}–${b}`, stroke: COLORS[i % COLORS.length], width: 1.5 });
    data.push(c.msc[i]);
  });
  series.push({ label: "threshold", stroke: "#000", width: 1, dash: [6, 4] });
  data.push(c.threshold_family);
  plot("coherence-plot", { height: 320, scales: { x: LOG, y: { range: [0, 1] } }, series,
    axes: [logAxis("frequency (Hz)"), { label: "magnitude-squared coherence" }] }, data);
  const peak = {};
  let coherent = 0;
  c.pairs.forEach(([a, b], i) => {
    let m = 0, f = null, above = false;
    c.msc[i].forEach((v, j) => {
      if (v > m) { m = v; f = c.f_hz[j]; }
      if (v > c.threshold_family[j]) above = true;
    });
    if (above) coherent += 1;
    peak[`${a}|${b}`] = peak[`${b}|${a}`] = { m, f, above };
  });
  const head = `<tr><th></th>${c.channels.map((n) => `<th>${n}</th>`).join("")}</tr>`;
  const rows = c.channels.map((a) => `<tr><th>${a}</th>${c.channels.map((b) => {
    const p = peak[`${a}|${b}`];
    if (a === b || !p) return "<td></td>";
    const shade = Math.round(255 * (1 - p.m));
    return `<td class="${p.above ? "coherent" : ""}" style="background:rgb(255,${shade},${shade})"` +
      ` title="highest ${fmt(p.m)} at ${fmt(p.f)} Hz">${fmt(p.m, 2)}</td>`;
  }).join("")}</tr>`).join("");
  const table = $("coherence-matrix");
  table.innerHTML = head + rows;
  table.dataset.coherent = String(coherent);
}

async function refreshCoherence() {
  try {
    let c = await getJSON("/coherence");
    // several devices: the document across all of them holds every stream's pairs and more
    if ((c.streams || []).includes("devices")) c = await getJSON("/coherence?stream=devices");
    drawCoherence(c);
  } catch (e) {
    $("coherence-info").textContent = String(e);
  }
}

// The interval now (+-% of the value) and, with serve --target, the recording still needed.
function planText(t, name) {
  const now = (t.relative_halfwidth || {})[name];
  let text = now === null || now === undefined ? "unresolved" : `±${fmt(100 * now, 2)} %`;
  const target = (t.target || {})[name];
  if (target !== undefined) {
    const more = t.time_to_target_s[name];
    text += ` → ±${fmt(100 * target, 2)} %: ` + (more === null ? "out of reach" :
      more === 0 ? "met" : `${fmt(more / 3600, 2)} h more`);
  }
  return text;
}

function drawCoefficients(c) {
  const rows = [];
  for (const t of c.model) {
    for (const [name, value] of Object.entries(t.params)) {
      const ci = t.ci95[name];
      const conv = (t.conventional || {})[name];
      // an amplitude whose interval reaches zero is no estimate: "not resolved", its bound
      const open = (t.unresolved || []).includes(name);
      rows.push(`<tr data-term="${t.term}"><td>${t.term}</td><td>${name}</td>
        <td>${open ? "not resolved" : fmt(value)}</td><td>${ci ? `${fmt(ci[0])} … ${fmt(ci[1])}` : ""}</td>
        <td>${(t.units || {})[name] || ""}</td><td>${conv ? (open ? "not resolved" : fmt(conv.value)) : ""}</td>
        <td>${conv && conv.ci95 ? `${fmt(conv.ci95[0])} … ${fmt(conv.ci95[1])}` : ""}</td>
        <td>${conv ? conv.units : ""}</td><td class="plan">${planText(t, name)}</td></tr>`);
    }
  }
  document.querySelector("#coefficients tbody").innerHTML = rows.join("");
  $("fit-info").textContent = c.intervals ?
    `fit of ${c.fitted_samples.toLocaleString()} samples, ` +
    `${c.intervals === "profile" ? "profile-likelihood" : "linearised"} intervals` : "no fit yet";
  $("record-info").textContent = `${c.n_samples.toLocaleString()} samples, ` +
    `${fmt(c.duration_s, 4)} s analysed in ${c.segments} segment(s) at ${fmt(c.fs_hz)} Hz`;
}

// The error's other parts beside the Allan one (from /coefficients): each about 1 when the
// model describes the sensor; a part not computed here says why.
function drawErrorParts(e) {
  if (!e) { $("error-parts").textContent = ""; return; }
  const part = (label, p, key, extra) => (p && p[key] != null ?
    `${label} ${fmt(p[key])}${extra(p)}` : `${label} n/a (${(p && p.reason) || "not computed"})`);
  const psd = part("PSD deviance/bin", e.psd, "deviance_per_bin", (p) => (p.outside_95 == null ?
    "" : ` (${fmt(100 * p.outside_95, 2)} % of ${p.bins} bins outside 95 %)`));
  const ho = part("hold-out χ²/dof", e.holdout, "chi2_per_dof", () => "");
  const td = part("time domain max|z|", e.time_domain, "statistic",
    (p) => ` (p ${fmt(p.p, 2)})`);
  $("error-parts").textContent = [psd, ho, td].join(" · ");
}

function drawModel(m) {
  $("error-value").textContent = m.error ? fmt(m.error.chi2_per_dof) : "–";
  $("error-value").dataset.value = m.error ? String(m.error.chi2_per_dof) : "";
  $("error-maxz").textContent = m.error ? `(max |z| ${fmt(m.error.max_abs_z)})` : "";
  // model entries are specifications ("sinusoid:f=2.7000342"): show held values briefly
  const shown = (t) => t.replace(/=([-+0-9.eE]+)/g, (_, v) => "=" + fmt(Number(v), 4));
  const names = m.model.map((t) => t.split(":")[0].split("#")[0]);
  $("model-terms").innerHTML = m.model.map((t) =>
    `<span class="term">${shown(t)} <button class="remove-term" data-term="${t}" title="remove">×</button></span>`
  ).join("");
  $("add-any").innerHTML = m.valid_terms.filter((t) => !names.includes(t)).map((t) =>
    `<button class="add-any" data-term="${t}">+ ${t}</button>`).join("");
  const h = m.history;
  $("history").innerHTML = h.slice(-12).reverse().map((p) =>
    `<li>rev ${p.revision}: Allan χ²/dof ${fmt(p.chi2_per_dof)} · PSD deviance/bin ` +
    `${fmt(p.psd_deviance_per_bin)} [${p.model.join(", ")}]</li>`).join("");
  if (h.length) {
    // seconds since the first fit on a plain axis: uPlot's default time axis would read the
    // service's clock as calendar dates, and with one point span years around it
    const t0 = h[0].time_s;
    const elapsed = (u, lo, hi) => (hi > lo ? [lo, hi] : [lo - 1, lo + 1]);
    plot("history-plot", { height: 150, scales: { x: { time: false, range: elapsed }, y: LOG },
      // each part is about 1 when the model is right; the PSD part is absent (a gap) until
      // the streaming PSD has an estimate
      series: [{ label: "s since the first fit" },
        { label: "Allan χ²/dof", stroke: "#d62728", width: 2, points: { show: true } },
        { label: "PSD deviance/bin", stroke: "#1f77b4", width: 2, points: { show: true } }],
      axes: [{ label: "time since the first fit (s)" }, logAxis("error part (1 = right)")] },
    [h.map((p) => p.time_s - t0), h.map((p) => Math.max(p.chi2_per_dof, 1e-3)),
      h.map((p) => (p.psd_deviance_per_bin == null ? null : Math.max(p.psd_deviance_per_bin, 1e-3)))]);
  }
}

function drawDiagnosis(d) {
  const items = d.suggestions.map((s) => {
    // an amplitude whose interval reaches zero is no estimate: its upper bound only
    const ps = Object.entries(s.params).map(([k, v]) => (s.unresolved || []).includes(k) ?
      `${k} not resolved (< ${fmt((s.ci95 || {})[k] ? s.ci95[k][1] : null)})` :
      `${k} = ${fmt(v)}`).join(", ");
    const model = s.apply && s.apply.model ? s.apply.model : "";
    // the action: add a term, cut the record, remove a term the record does not resolve,
    // or replace the model's filter by another kind
    const verb = s.action === "remove" ? "Remove" : s.action === "cut" ? "Cut at" :
      s.action === "replace" ? "Replace" : "Add";
    return `<li><button class="add-term" data-term="${s.term}" data-model="${model}">${verb} ${s.label || s.term}</button>
      <span class="${s.significant ? "sig" : ""}">${s.significant ? "significant" : "not significant"}</span>:
      χ²/dof after ${fmt(s.chi2_per_dof_after)}${s.p_value !== null && s.p_value !== undefined ? `, p = ${fmt(s.p_value, 2)}` : ""} (${ps})<span class="why">${s.why}</span></li>`;
  });
  const found = (d.findings || []).map((f) => `<li class="finding">${f.why}</li>`);
  items.push(...found);
  const note = document.createElement("li");
  note.textContent = d.note || "no candidate terms left";
  $("suggestions").innerHTML = items.join("");
  if (!d.suggestions.length || d.note) $("suggestions").appendChild(note);
}

async function refresh() {
  if (state.busy) { state.pending = true; return; }
  state.busy = true;
  try {
    const ch = await getJSON("/channels");
    const sel = $("channel");
    if (sel.options.length !== ch.channels.length) {
      sel.innerHTML = ch.channels.map((c) => `<option>${c}</option>`).join("");
    }
    if (!ch.channels.length) return;
    if (!state.channel || !ch.channels.includes(state.channel)) state.channel = ch.channels[0];
    sel.value = state.channel;
    const q = `?channel=${encodeURIComponent(state.channel)}`;
    const changes = state.changes;
    const [a, p, c, m, d] = await Promise.all([getJSON(`/allan${q}`), getJSON(`/psd${q}`),
      getJSON("/coefficients"), getJSON(`/model${q}`), getJSON(`/diagnosis${q}`)]);
    if (changes !== state.changes) { state.pending = true; return; }  // the refresh queued redraws
    drawAllan(a); drawPsd(p); drawCoefficients(c.channels[state.channel]); drawModel(m);
    drawErrorParts(c.channels[state.channel].error);
    drawDiagnosis(d);
    await refreshCoherence();
    state.renders += 1;
    document.body.dataset.renders = String(state.renders);
  } catch (e) {
    $("action-msg").textContent = String(e);
  } finally {
    state.busy = false;
    state.lastRefresh = Date.now();
    if (state.pending) { state.pending = false; setTimeout(refresh, 300); }
  }
}

async function changeModel(body) {
  const headers = { "Content-Type": "application/json" };
  if (token) headers["X-Imunoise-Token"] = token;
  state.changes += 1;
  const r = await fetch("/model", { method: "POST", headers,
    body: JSON.stringify({ channel: state.channel, ...body }) });
  const j = await r.json();
  state.changes += 1;
  if (!r.ok) { $("action-msg").textContent = `refused: ${j.detail}`; return; }
  $("action-msg").textContent = `model ${j.model.join(" + ")}: χ²/dof ` +
    `${fmt(j.error_before.chi2_per_dof)} → ${fmt(j.error_after.chi2_per_dof)}`;
  await refresh();
}

document.addEventListener("click", (ev) => {
  const b = ev.target.closest("button");
  if (!b) return;
  if (b.classList.contains("add-term") && b.dataset.model) {
    changeModel({ model: b.dataset.model });  // the suggestion's apply.model, as stated
  } else if (b.classList.contains("add-term") || b.classList.contains("add-any")) {
    changeModel({ add: b.dataset.term });
  }
  if (b.classList.contains("remove-term")) changeModel({ remove: b.dataset.term });
});
$("channel").addEventListener("change", (ev) => { state.channel = ev.target.value; refresh(); });

function status(h) {
  const s = $("status");
  s.textContent = `${h.state} · ${Number(h.samples.received).toLocaleString()} samples · ` +
    `dropped ${h.samples.dropped} · ${h.file ? `writing ${h.file.split("/").pop()}` : "not recording"}`;
  s.classList.toggle("bad", h.status !== "ok" || h.samples.dropped > 0);
}

function connect() {
  const es = new EventSource("/events");
  es.addEventListener("update", (ev) => {
    const h = JSON.parse(ev.data);
    status(h);
    if (Date.now() - state.lastRefresh > 1000) refresh();
  });
  es.onerror = () => { $("status").textContent = "disconnected: retrying…";
    $("status").classList.add("bad"); };
}

refresh();
connect();
