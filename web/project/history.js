// Run history: one row per run with its status, time and headline mIoU per result row, the compare
// check boxes, exports, resume and the run log.

import { get, patch } from "../api.js";
import { duration, fmtPct, fmtSeconds, fmtTime, h, replace, statusChip } from "../dom.js";
import { exportActions } from "./exports.js";
import { RESUME_TITLE } from "./run-panel.js";

function miou(run, row, protocol) {
  const table = run.summary && run.summary[protocol];
  return table ? table[row] : undefined;
}

function rowsOf(runs, protocol) {
  const rows = [];
  for (const r of runs) {
    const table = r.summary && r.summary[protocol];
    if (table) for (const k of Object.keys(table)) if (!rows.includes(k)) rows.push(k);
  }
  return rows;
}

/** Until the user ticks a box, the two latest runs with metrics are compared. */
function defaultCompare(state) {
  if (state.compareTouched) return;
  state.compare = new Set(state.runs.filter((r) => r.has_metrics).slice(0, 2).map((r) => r.id));
}

function runActions(ctx, run) {
  const { state } = ctx;
  const out = exportActions(ctx, run);
  if (run.resumable) {
    out.push(h("button", { class: "btn small", title: RESUME_TITLE, onclick: () => ctx.actions.runAction(run, "resume") }, "Resume"));
  }
  out.push(
    h(
      "button",
      {
        class: "btn small ghost",
        dataset: { action: "note" },
        title: run.note ? "Edit the run's note" : "Add a note to the run",
        onclick: async () => {
          const text = window.prompt(`Note for run ${run.number}`, run.note || "");
          if (text === null) return;
          try {
            const updated = await patch(`/runs/${run.id}`, { note: text });
            run.note = updated.note;
            ctx.render.runs();
            await ctx.render.compare();
          } catch (err) {
            ctx.toast(err.message, "error");
          }
        },
      },
      "Note",
    ),
  );
  out.push(
    h(
      "button",
      {
        class: "btn small ghost",
        onclick: () => {
          if (state.openLogs.has(run.id)) state.openLogs.delete(run.id);
          else state.openLogs.add(run.id);
          ctx.render.runs();
        },
      },
      state.openLogs.has(run.id) ? "Hide log" : "Log",
    ),
  );
  return out;
}

function runRows(ctx, run, rows) {
  const { state } = ctx;
  const dur = duration(run);
  const tr = h(
    "tr",
    { dataset: { runId: String(run.id), status: run.status } },
    h(
      "td",
      {},
      h("input", {
        type: "checkbox",
        class: "compare-box",
        disabled: !run.has_metrics,
        checked: state.compare.has(run.id),
        "aria-label": `Compare run ${run.number}`,
        onchange: async (e) => {
          state.compareTouched = true;
          if (e.target.checked) state.compare.add(run.id);
          else state.compare.delete(run.id);
          await ctx.render.compare();
        },
      }),
    ),
    h("td", {}, `#${run.number}`),
    h("td", {}, statusChip(run.status)),
    h("td", { class: "muted" }, fmtTime(run.started_at || run.created_at)),
    h("td", { class: "muted" }, dur !== null && ctx.terminal.has(run.status) ? fmtSeconds(dur) : ctx.active.has(run.status) ? "…" : ""),
    rows.map((r) => h("td", { class: "num" }, fmtPct(miou(run, r, state.protocol)))),
    h("td", { class: "run-actions" }, runActions(ctx, run)),
  );
  const out = [tr];
  if (run.note) {
    out.push(h("tr", { class: "sub run-note-row" }, h("td", {}), h("td", { colspan: 5 + rows.length, class: "muted small run-note-text" }, `Note: ${run.note}`)));
  }
  if (run.error && !ctx.active.has(run.status)) {
    out.push(h("tr", { class: "sub" }, h("td", {}), h("td", { colspan: 5 + rows.length, class: "error small" }, run.error)));
  }
  const warnings = (run.progress && run.progress.warnings) || [];
  if (warnings.length && !ctx.active.has(run.status)) {
    out.push(h("tr", { class: "sub" }, h("td", {}), h("td", { colspan: 5 + rows.length, class: "run-warnings small" }, warnings.join(" · "))));
  }
  if (state.openLogs.has(run.id)) {
    const pre = h("pre", { class: "log" }, "loading…");
    get(`/runs/${run.id}/logs`).then(
      (log) => (pre.textContent = (log.truncated ? "…\n" : "") + (log.text || "(empty)")),
      (err) => (pre.textContent = err.message),
    );
    out.push(h("tr", { class: "sub" }, h("td", {}), h("td", { colspan: 5 + rows.length }, pre)));
  }
  return out;
}

export function renderRuns(ctx) {
  const { state } = ctx;
  defaultCompare(state);
  const runs = state.runs;
  const rows = rowsOf(runs, state.protocol);
  const table = h(
    "table",
    { class: "runs-table" },
    h(
      "thead",
      {},
      h(
        "tr",
        {},
        h("th", { title: "Compare" }, "⇆"),
        h("th", {}, "Run"),
        h("th", {}, "Status"),
        h("th", {}, "Started"),
        h("th", {}, "Time"),
        rows.map((r) => h("th", { class: "num" }, `${r} mIoU`)),
        h("th", {}, ""),
      ),
    ),
    h("tbody", {}, runs.map((run) => runRows(ctx, run, rows))),
  );
  replace(
    ctx.els.runs,
    h("div", { class: "card-head" }, h("h2", {}, "Run history"), h("span", { class: "muted small" }, "mIoU in %, camera-view protocol unless chosen below")),
    runs.length ? h("div", { class: "table-wrap" }, table) : h("p", { class: "muted" }, "No runs yet."),
  );
}
