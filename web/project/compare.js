// Metrics of the runs ticked in the history, side by side: a headline with the camera-view figures beside
// the share of *all* points labeled (what an export leaves unlabeled), a table per result row, a per-class
// IoU table with a Δ column (newest compared run against the one before it), what changed between those two
// runs (GET /runs/{id}/compare/{base}: prompts, classes, parameters), the object scores (panoptic quality,
// moving-object IoU, S_assoc: the metrics' `objects`, with the same Δ) and a per-class IoU chart.

import { get } from "../api.js";
import { RUN_COLORS, iouChart } from "../chart.js";
import { fmtPct, h, replace } from "../dom.js";
import { changeList } from "./next-run.js";

async function comparisonOf(state, runId, baseId) {
  const key = `${runId}:${baseId}`;
  if (!state.comparisons) state.comparisons = new Map();
  if (!state.comparisons.has(key)) state.comparisons.set(key, await get(`/runs/${runId}/compare/${baseId}`));
  return state.comparisons.get(key);
}

function fmtDelta(x) {
  if (x === null || x === undefined || Number.isNaN(x)) return "–";
  const v = 100 * x;
  return `${v > 0 ? "+" : v < 0 ? "−" : "±"}${Math.abs(v).toFixed(1)}`;
}

/** The camera-view figures of the newest run's chosen row beside the share of all its points labeled. */
function headline(state, run, m, several) {
  const camera = (m.protocols.camera || {})[state.row];
  const all = (m.labeled_share_all_points || {})[state.row];
  return h(
    "p",
    { class: "metrics-headline", id: "metrics-headline" },
    h("strong", {}, `Run ${run.number}${state.metricsSequence !== null ? ` · sequence ${state.metricsSequence}` : several ? " · overall" : ""} · ${state.row}: `),
    camera ? `camera view mIoU ${fmtPct(camera.miou)} %, ${fmtPct(camera.labeled_share)} % of in-view ground-truth points labeled · ` : "",
    h("span", { id: "all-points-labeled", title: "Share of every point of every evaluated scan that got a label: what the exported .label files label" }, `${fmtPct(all)} % of all points labeled`),
  );
}

/** Runs whose export the "apply corrections" job changed after their evaluation: their figures predate it. */
function staleNote(runs, all) {
  const stale = runs.filter((_, i) => all[i].before_corrections).map((r) => `#${r.number}`);
  if (!stale.length) return null;
  return h("p", { class: "muted small", id: "metrics-before-corrections" },
    `Run ${stale.join(", ")}: these figures were measured before the corrections since applied to its export; a re-run measures them with the corrections.`);
}

/** The view of a protocol over merged classes (the paper's 11) in the newest compared run that has it. */
function protocolView(all, protocol) {
  for (let i = all.length - 1; i >= 0; i -= 1) {
    const view = (all[i].metrics.views || {})[protocol];
    if (view) return view;
  }
  return null;
}

/** A protocol's classes: the merged ones of its view, else the newest run's schema classes. */
function protocolClasses(all, protocol) {
  const view = protocolView(all, protocol);
  return view ? view.class_names : all[all.length - 1].class_names;
}

const PROTOCOL_LABELS = { camera: "camera view", common: "camera view, same points", all: "all points", paper: "paper's 11 classes (camera view)" };

function classTable(state, runs, all, comparison) {
  const names = protocolClasses(all, state.protocol);
  const two = comparison !== null;
  const rowDelta = two ? comparison.rows.find((r) => r.protocol === state.protocol && r.row === state.row) : null;
  const byName = new Map(rowDelta ? rowDelta.classes.map((c) => [c.name, c]) : []);
  const iouOf = (i) => ((all[i].metrics.protocols[state.protocol] || {})[state.row] || {}).iou || {};
  const last = iouOf(all.length - 1);
  const prev = two ? iouOf(all.length - 2) : {};
  const nameList = two && rowDelta ? rowDelta.classes.map((c) => c.name) : names;
  const a = runs[runs.length - 1];
  const b = two ? runs[runs.length - 2] : null;
  return h(
    "table",
    { class: "metrics-table class-table", id: "class-table" },
    h(
      "thead",
      {},
      h("tr", {}, h("th", {}, "Class"), two ? h("th", { class: "num" }, `#${b.number} IoU`) : null, h("th", { class: "num" }, `#${a.number} IoU`), two ? h("th", { class: "num", title: `run ${a.number} − run ${b.number}` }, "Δ") : null),
    ),
    h(
      "tbody",
      {},
      nameList.map((n) => {
        const d = byName.get(n);
        const computed = two && typeof last[n] === "number" && typeof prev[n] === "number" ? last[n] - prev[n] : null;
        const delta = d ? d.delta : computed;
        return h(
          "tr",
          { dataset: { class: n } },
          h("td", {}, n),
          two ? h("td", { class: "num" }, fmtPct(d ? d.base_iou : prev[n])) : null,
          h("td", { class: "num iou" }, fmtPct(d ? d.iou : last[n])),
          two ? h("td", { class: `num delta${delta > 0 ? " up" : delta < 0 ? " down" : ""}` }, fmtDelta(delta)) : null,
        );
      }),
    ),
  );
}

/** The object scores shown, as [key, label, title, (objects) => value]; in %, as the CLI's table. */
const OBJECT_SCORES = [
  ["pq-camera", "PQ · camera view", "panoptic quality over every class, points in the camera view", (o) => o.camera.PQ],
  ["pq-things-camera", "PQ things · camera view", "panoptic quality of the thing classes (tracked objects)", (o) => o.camera.PQ_things],
  ["pq-stuff-camera", "PQ stuff · camera view", "panoptic quality of the stuff classes", (o) => o.camera.PQ_stuff],
  ["pq-all", "PQ · all points", "panoptic quality over every class, all points", (o) => o.all.PQ],
  ["pq-things-all", "PQ things · all points", "panoptic quality of the thing classes, all points", (o) => o.all.PQ_things],
  ["mos-iou", "MOS IoU", "moving-object IoU of the moving points, all points (as evaluate_mos.py)", (o) => (o.motion || {}).mos_iou],
  ["s-assoc", "S_assoc", "LSTQ's association score: one id per object through the sequence", (o) => (o.motion || {}).s_assoc],
];
const NO_OBJECTS = "—";

/**
 * The object scores of the newest compared run and the one before it, with Δ. A run without them (tracking
 * off, or evaluated before object scores existed) shows "—"; a score without ground truth to measure
 * (no moving points) shows "–".
 */
function objectTable(runs, all) {
  const two = runs.length >= 2;
  const objs = all.map((m) => m.metrics.objects || null);
  const a = runs[runs.length - 1];
  const b = two ? runs[runs.length - 2] : null;
  const oa = objs[objs.length - 1];
  const ob = two ? objs[objs.length - 2] : null;
  const cell = (o, get) => (o ? fmtPct(get(o)) : NO_OBJECTS);
  const num = (o, get) => (o && typeof get(o) === "number" ? get(o) : null);
  const noObjects = "no object scores: the run tracked no objects (tracking off) or predates them";
  return h(
    "table",
    { class: "metrics-table object-table", id: "object-table" },
    h(
      "thead",
      {},
      h("tr", {}, h("th", {}, "Score"), two ? h("th", { class: "num", title: ob ? "" : noObjects }, `#${b.number}`) : null, h("th", { class: "num", title: oa ? "" : noObjects }, `#${a.number}`), two ? h("th", { class: "num", title: `run ${a.number} − run ${b.number}` }, "Δ") : null),
    ),
    h(
      "tbody",
      {},
      OBJECT_SCORES.map(([key, label, title, get]) => {
        const va = num(oa, get);
        const vb = two ? num(ob, get) : null;
        const delta = va !== null && vb !== null ? va - vb : null;
        return h(
          "tr",
          { dataset: { score: key } },
          h("td", { title }, label),
          two ? h("td", { class: "num" }, cell(ob, get)) : null,
          h("td", { class: "num score" }, cell(oa, get)),
          two ? h("td", { class: `num delta${delta > 0 ? " up" : delta < 0 ? " down" : ""}` }, fmtDelta(delta)) : null,
        );
      }),
    ),
  );
}

/** A run's metrics: its own (overall for a run of several sequences), or one sequence's. */
async function metricsOf(state, runId, sequence = null) {
  const key = sequence === null ? runId : `${runId}:${sequence}`;
  if (!state.metrics.has(key)) {
    const query = sequence === null ? "" : `?sequence=${encodeURIComponent(sequence)}`;
    state.metrics.set(key, await get(`/runs/${runId}/metrics${query}`));
  }
  return state.metrics.get(key);
}

/** The sequence picker of the metrics card (a run of several sequences): overall or one sequence. */
function sequenceSelect(ctx, names) {
  const { state } = ctx;
  if (names.length < 2) return null;
  return h(
    "label",
    { class: "inline" },
    "Sequence ",
    h(
      "select",
      { id: "metrics-sequence", onchange: (e) => { state.metricsSequence = e.target.value || null; ctx.render.compare(); } },
      h("option", { value: "", selected: state.metricsSequence === null }, "overall"),
      names.map((n) => h("option", { value: n, selected: n === state.metricsSequence }, n)),
    ),
  );
}

function runDot(i) {
  return h("span", { class: "run-dot", style: { background: RUN_COLORS[i % RUN_COLORS.length] } });
}

function metricsTable(state, runs, all) {
  return h(
    "table",
    { class: "metrics-table", id: "metrics-table" },
    h("thead", {}, h("tr", {}, h("th", {}, "Run"), h("th", {}, "Labels"), h("th", { class: "num" }, "mIoU"), h("th", { class: "num" }, "cat. mIoU"), h("th", { class: "num", title: "share of ground-truth points labeled (in the camera view for that protocol)" }, "labeled"), h("th", { class: "num", title: "share of all points labeled, ground truth or not" }, "all pts labeled"), h("th", { class: "num" }, "× points"))),
    h(
      "tbody",
      {},
      runs.map((run, i) => {
        const m = all[i].metrics;
        const table = m.protocols[state.protocol] || {};
        return Object.entries(table).map(([row, v], j) =>
          h(
            "tr",
            { class: row === state.row ? "hl" : "", dataset: { runId: String(run.id), row } },
            h("td", {}, j === 0 ? runDot(i) : null, j === 0 ? `#${run.number}` : ""),
            h("td", {}, row),
            h("td", { class: "num strong" }, fmtPct(v.miou)),
            h("td", { class: "num" }, fmtPct(v.category_miou)),
            h("td", { class: "num" }, fmtPct(v.labeled_share)),
            h("td", { class: "num all-labeled" }, fmtPct((m.labeled_share_all_points || {})[row])),
            h("td", { class: "num" }, m.coverage_ratio && m.coverage_ratio[row] ? m.coverage_ratio[row].toFixed(2) : "–"),
          ),
        );
      }),
    ),
  );
}

export async function renderCompare(ctx) {
  const { state } = ctx;
  const el = ctx.els.compare;
  const runs = state.runs.filter((r) => state.compare.has(r.id)).reverse();
  if (!runs.length) {
    replace(el, h("h2", {}, "Metrics"), h("p", { class: "muted" }, "Finished runs on data with ground truth show their metrics here; tick runs in the history to compare them."));
    return;
  }
  if (state.metricsSequence === undefined) state.metricsSequence = null;
  let all;
  let seqNames = [];
  try {
    const own = await Promise.all(runs.map((r) => metricsOf(state, r.id)));
    seqNames = own[own.length - 1].sequences || [];
    if (!seqNames.includes(state.metricsSequence)) state.metricsSequence = null;
    all = state.metricsSequence === null ? own : await Promise.all(runs.map((r) => metricsOf(state, r.id, state.metricsSequence)));
  } catch (err) {
    replace(el, h("div", { class: "card-head" }, h("h2", {}, "Metrics"), sequenceSelect(ctx, seqNames)), h("p", { class: "error" }, err.message));
    return;
  }
  // Every protocol any compared run has (the paper's exists only for runs with SemanticKITTI's classes).
  const protocols = [];
  for (const m of all) for (const p of Object.keys(m.metrics.protocols)) if (!protocols.includes(p)) protocols.push(p);
  if (!protocols.includes(state.protocol)) state.protocol = protocols[0];
  const rowNames = [];
  for (const m of all) for (const r of m.metrics.rows.length ? m.metrics.rows : Object.keys(m.metrics.protocols[state.protocol] || {})) if (!rowNames.includes(r)) rowNames.push(r);
  if (!rowNames.includes(state.row)) state.row = rowNames.includes("voxel") ? "voxel" : rowNames[rowNames.length - 1];

  const protoSel = h(
    "select",
    { id: "protocol-select", onchange: (e) => { state.protocol = e.target.value; ctx.render.runs(); ctx.render.compare(); } },
    protocols.map((p) => h("option", { value: p, selected: p === state.protocol, title: (all[all.length - 1].metrics.descriptions || {})[p] || "" }, PROTOCOL_LABELS[p] || p)),
  );
  const notes = all[all.length - 1].metrics.notes || {};
  const protocolNotes = Object.keys(notes).length
    ? h("p", { class: "muted small", id: "protocol-notes" }, Object.entries(notes).map(([p, t]) => `${PROTOCOL_LABELS[p] || p}: ${t}`).join(" · "))
    : null;
  const rowSel = h(
    "select",
    { id: "row-select", onchange: (e) => { state.row = e.target.value; ctx.render.compare(); } },
    rowNames.map((r) => h("option", { value: r, selected: r === state.row }, r)),
  );

  const colorOf = new Map(state.classes.map((c) => [c.name, c.hex]));
  const names = protocolClasses(all, state.protocol);
  // A merged class takes the colour of its first schema class (manmade: building's, as in the paper).
  const merge = (protocolView(all, state.protocol) || {}).merge || {};
  const classRows = names.map((n) => ({ name: n, color: colorOf.get(n) || colorOf.get((merge[n] || [])[0]) || "#999999" }));
  const series = runs.map((run, i) => {
    const row = (all[i].metrics.protocols[state.protocol] || {})[state.row];
    return { label: `run ${run.number}`, iou: row ? row.iou : {} };
  });
  const legend = h("div", { class: "legend" }, runs.map((run, i) => h("span", { title: run.note || "" }, runDot(i), `run ${run.number}`, run.note ? h("em", { class: "muted small" }, ` “${run.note}”`) : null)));
  let comparison = null;
  if (runs.length >= 2) {
    try {
      comparison = await comparisonOf(state, runs[runs.length - 1].id, runs[runs.length - 2].id);
      // The server's Δ rows are of the runs' own (overall) figures; one sequence's Δ is computed here.
      if (state.metricsSequence !== null) comparison = { ...comparison, rows: [] };
    } catch (err) {
      comparison = null;
    }
  }
  const latest = runs[runs.length - 1];
  replace(
    el,
    h("div", { class: "card-head" }, h("h2", {}, "Metrics"), h("div", { class: "row" }, sequenceSelect(ctx, seqNames), h("label", { class: "inline" }, "Protocol ", protoSel), h("label", { class: "inline" }, "Row ", rowSel))),
    headline(state, latest, all[all.length - 1].metrics, seqNames.length > 1),
    protocolNotes,
    staleNote(runs, all),
    h("div", { class: "table-wrap" }, metricsTable(state, runs, all)),
    h("h3", { class: "chart-title" }, comparison ? `Per-class IoU (%) · ${state.row} labels · run ${latest.number} against run ${runs[runs.length - 2].number}` : `Per-class IoU (%) · ${state.row} labels`),
    h("div", { class: "table-wrap" }, classTable(state, runs, all, comparison)),
    h("h3", { class: "chart-title" }, runs.length >= 2 ? `Object scores (%) · run ${latest.number} against run ${runs[runs.length - 2].number}` : "Object scores (%)"),
    state.metricsSequence === null && seqNames.length > 1
      ? h("p", { class: "muted small", id: "object-scores-note" }, "Objects are tracked per sequence: pick a sequence above for its object scores.")
      : null,
    h("div", { class: "table-wrap" }, objectTable(runs, all)),
    comparison ? h("h3", { class: "chart-title" }, `What changed from run ${runs[runs.length - 2].number} to run ${latest.number}`) : null,
    comparison ? changeList(comparison.changes, "run-changes") : null,
    h("h3", { class: "chart-title" }, "Per-class IoU chart"),
    legend,
    h("div", { id: "iou-chart" }, iouChart(series, classRows)),
  );
}
