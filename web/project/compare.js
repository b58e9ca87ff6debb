// Metrics of the runs ticked in the history, side by side: a table per result row and a per-class IoU chart.

import { get } from "../api.js";
import { RUN_COLORS, iouChart } from "../chart.js";
import { fmtPct, h, replace } from "../dom.js";

async function metricsOf(state, runId) {
  if (!state.metrics.has(runId)) state.metrics.set(runId, await get(`/runs/${runId}/metrics`));
  return state.metrics.get(runId);
}

function runDot(i) {
  return h("span", { class: "run-dot", style: { background: RUN_COLORS[i % RUN_COLORS.length] } });
}

function metricsTable(state, runs, all) {
  return h(
    "table",
    { class: "metrics-table", id: "metrics-table" },
    h("thead", {}, h("tr", {}, h("th", {}, "Run"), h("th", {}, "Labels"), h("th", { class: "num" }, "mIoU"), h("th", { class: "num" }, "cat. mIoU"), h("th", { class: "num" }, "labeled"), h("th", { class: "num" }, "× points"))),
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
  let all;
  try {
    all = await Promise.all(runs.map((r) => metricsOf(state, r.id)));
  } catch (err) {
    replace(el, h("h2", {}, "Metrics"), h("p", { class: "error" }, err.message));
    return;
  }
  const protocols = Object.keys(all[0].metrics.protocols);
  if (!protocols.includes(state.protocol)) state.protocol = protocols[0];
  const rowNames = [];
  for (const m of all) for (const r of m.metrics.rows.length ? m.metrics.rows : Object.keys(m.metrics.protocols[state.protocol])) if (!rowNames.includes(r)) rowNames.push(r);
  if (!rowNames.includes(state.row)) state.row = rowNames.includes("voxel") ? "voxel" : rowNames[rowNames.length - 1];

  const protoSel = h(
    "select",
    { id: "protocol-select", onchange: (e) => { state.protocol = e.target.value; ctx.render.runs(); ctx.render.compare(); } },
    protocols.map((p) => h("option", { value: p, selected: p === state.protocol }, p === "camera" ? "camera view (paper)" : "all points")),
  );
  const rowSel = h(
    "select",
    { id: "row-select", onchange: (e) => { state.row = e.target.value; ctx.render.compare(); } },
    rowNames.map((r) => h("option", { value: r, selected: r === state.row }, r)),
  );

  const colorOf = new Map(state.classes.map((c) => [c.name, c.hex]));
  const names = all[all.length - 1].class_names;
  const classRows = names.map((n) => ({ name: n, color: colorOf.get(n) || "#999999" }));
  const series = runs.map((run, i) => {
    const row = (all[i].metrics.protocols[state.protocol] || {})[state.row];
    return { label: `run ${run.number}`, iou: row ? row.iou : {} };
  });
  const legend = h("div", { class: "legend" }, runs.map((run, i) => h("span", {}, runDot(i), `run ${run.number}`)));
  replace(
    el,
    h("div", { class: "card-head" }, h("h2", {}, "Metrics"), h("div", { class: "row" }, h("label", { class: "inline" }, "Protocol ", protoSel), h("label", { class: "inline" }, "Chart ", rowSel))),
    h("div", { class: "table-wrap" }, metricsTable(state, runs, all)),
    h("h3", { class: "chart-title" }, `Per-class IoU (%) · ${state.row} labels`),
    legend,
    h("div", { id: "iou-chart" }, iouChart(series, classRows)),
  );
}
