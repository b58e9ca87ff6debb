// One project: run with live per-stage progress, run history, metrics comparison, class and prompt
// editor, pipeline parameters, exports and the link to the 3D viewer.

import { ApiError, del, enc, get, patch, post, url } from "./api.js";
import { RUN_COLORS, iouChart } from "./chart.js";
import { duration, fmtPct, fmtSeconds, fmtTime, h, replace } from "./dom.js";

const STAGE_LABELS = {
  "generate demo": "Generate demo",
  labels2d: "2D labels",
  project: "Projection",
  fuse: "Voxel fusion",
  smooth: "kNN smoothing",
  "3dcn": "3D-CN",
  label_points: "Point labels",
  evaluate: "Evaluation",
  export: "Export",
};
const ACTIVE = new Set(["queued", "running"]);
const TERMINAL = new Set(["done", "failed", "cancelled", "interrupted"]);

const PARAMS = [
  { name: "labeler", label: "2D labeler", type: "select", options: [["simulated", "simulated (from 2D ground truth)"], ["grounded-sam", "Grounding DINO + SAM"]] },
  { name: "threshold", label: "Box threshold", type: "number", step: 0.01, min: 0, max: 1 },
  { name: "voxel_size", label: "Voxel size (m)", type: "number", step: 0.05, min: 0.01 },
  { name: "k", label: "kNN smoothing k", type: "number", step: 1, min: 1 },
  { name: "cluster_gap", label: "Depth-cluster gap (m)", type: "number", step: 0.1, min: 0 },
  { name: "consistency", label: "3D Consistency Network", type: "checkbox" },
  { name: "share", label: "3D-CN label share", type: "number", step: 0.05, min: 0, max: 1 },
  { name: "temperature", label: "3D-CN temperature", type: "number", step: 0.1, min: 0 },
  { name: "iterations", label: "3D-CN iterations", type: "number", step: 1, min: 1 },
];

function statusChip(status) {
  return h("span", { class: `chip status-${status}` }, status);
}

function miou(run, row, protocol = "camera") {
  const table = run.summary && run.summary[protocol];
  return table ? table[row] : undefined;
}

export async function renderProject(root, projectId, { toast }) {
  const state = {
    project: null,
    classes: [],
    runs: [],
    health: null,
    stream: null,
    streamRun: null,
    compare: new Set(),
    compareTouched: false,
    metrics: new Map(),
    protocol: "camera",
    row: null,
    openLogs: new Set(),
  };
  let disposed = false;

  const els = {
    head: h("div", { class: "page-head" }),
    run: h("section", { class: "card", id: "run-panel" }),
    runs: h("section", { class: "card", id: "runs" }),
    compare: h("section", { class: "card", id: "compare" }),
    classes: h("section", { class: "card", id: "classes" }),
    params: h("section", { class: "card", id: "params" }),
  };

  // ------------------------------------------------------------------------------------------ data
  async function loadAll() {
    const [project, classes, runs, health] = await Promise.all([
      get(`/projects/${projectId}`),
      get(`/projects/${projectId}/classes`),
      get(`/projects/${projectId}/runs`),
      get("/health"),
    ]);
    state.project = project;
    state.classes = classes.data;
    state.runs = runs.data;
    state.health = health;
  }

  async function refreshRuns() {
    const [project, runs] = await Promise.all([get(`/projects/${projectId}`), get(`/projects/${projectId}/runs`)]);
    state.project = project;
    state.runs = runs.data;
  }

  function latestRun() {
    return state.runs.length ? state.runs[0] : null;
  }

  // --------------------------------------------------------------------------------- live progress
  function follow(run) {
    if (!run || !ACTIVE.has(run.status)) return;
    if (state.stream && state.streamRun === run.id) return;
    if (state.stream) state.stream.close();
    const es = new EventSource(url(`/runs/${run.id}/events`));
    state.stream = es;
    state.streamRun = run.id;
    es.addEventListener("progress", (ev) => {
      const progress = JSON.parse(ev.data);
      const r = state.runs.find((x) => x.id === progress.run_id);
      if (r) {
        const changed = r.status !== progress.status;
        r.progress = progress;
        r.status = progress.status;
        if (changed && state.project.active_run) {
          state.project.active_run.status = progress.status;
          renderHead();
        }
      }
      renderRunPanel();
    });
    es.addEventListener("end", async () => {
      es.close();
      state.stream = null;
      state.streamRun = null;
      if (disposed) return;
      await refreshRuns();
      const r = state.runs.find((x) => x.id === run.id);
      if (r) toast(`Run ${r.number} ${r.status}${r.error ? `: ${r.error}` : ""}`, r.status === "done" ? "info" : "error");
      renderHead();
      renderRunPanel();
      renderRuns();
      await renderCompare();
    });
  }

  async function startRun() {
    try {
      const run = await post(`/projects/${projectId}/runs`, {});
      await refreshRuns();
      renderHead();
      renderRunPanel();
      renderRuns();
      follow(state.runs.find((r) => r.id === run.id) || run);
    } catch (err) {
      toast(err.message, "error");
    }
  }

  async function runAction(run, action) {
    try {
      await post(`/runs/${run.id}/${action}`, {});
      await refreshRuns();
      renderHead();
      renderRunPanel();
      renderRuns();
      follow(state.runs.find((r) => r.id === run.id));
    } catch (err) {
      toast(err.message, "error");
    }
  }

  // ------------------------------------------------------------------------------------------ head
  function renderHead() {
    const p = state.project;
    const active = p.active_run;
    const lastDone = state.runs.find((r) => r.status === "done");
    const title = h("h1", { id: "project-name" }, p.name);
    const rename = h("button", {
      class: "btn ghost small",
      title: "Rename project",
      onclick: () => {
        const input = h("input", { value: p.name, class: "title-input", maxlength: 120 });
        const commit = async () => {
          const name = input.value.trim();
          if (name && name !== p.name) {
            try {
              state.project = await patch(`/projects/${projectId}`, { name });
            } catch (err) {
              toast(err.message, "error");
            }
          }
          renderHead();
        };
        input.addEventListener("keydown", (e) => {
          if (e.key === "Enter") commit();
          if (e.key === "Escape") renderHead();
        });
        input.addEventListener("blur", commit);
        title.replaceWith(input);
        input.focus();
      },
    }, "Rename");
    const runBtn = h(
      "button",
      { class: "btn primary", id: "run-button", disabled: Boolean(active), onclick: startRun },
      active ? `Run ${active.number} ${active.status}…` : "▶ Run pipeline",
    );
    const viewerBtn =
      state.health && state.health.viewer
        ? h(
            "button",
            {
              class: "btn",
              id: "viewer-button",
              disabled: !lastDone,
              title: lastDone ? `Review run ${lastDone.number} in 3D` : "Needs a finished run",
              onclick: async () => {
                const win = window.open("about:blank", "_blank");
                try {
                  const v = await post(`/projects/${projectId}/viewer`, { run_id: lastDone.id });
                  if (win) win.location = url(v.url);
                } catch (err) {
                  if (win) win.close();
                  toast(err.message, "error");
                }
              },
            },
            "Open 3D viewer",
          )
        : null;
    const deleteBtn = h(
      "button",
      {
        class: "btn danger ghost",
        id: "delete-project",
        onclick: async () => {
          if (!window.confirm(`Delete project “${p.name}”, its run history and run folders? The dataset and any labels exported into it stay.`)) return;
          try {
            await del(`/projects/${projectId}`);
            window.location.hash = "#/";
          } catch (err) {
            toast(err.message, "error");
          }
        },
      },
      "Delete",
    );
    const ds = p.dataset;
    replace(
      els.head,
      h("a", { href: "#/", class: "back" }, "← Projects"),
      h("div", { class: "title-row" }, title, rename, p.is_demo ? h("span", { class: "chip demo" }, "demo") : null),
      h(
        "p",
        { class: "muted dataset-line" },
        ds.kind === "demo" ? "Built-in demo sequence · " : "",
        h("code", {}, ds.path),
        ds.frames !== null ? ` · ${ds.frames} frames` : " · not generated yet",
        ds.has_ground_truth ? " · ground truth" : "",
      ),
      h("div", { class: "actions" }, runBtn, viewerBtn, deleteBtn),
    );
  }

  // ------------------------------------------------------------------------------------- run panel
  function stageRow(stage) {
    const pct = Math.max(0, Math.min(100, stage.percent));
    let detail = "";
    if (stage.status === "running") {
      detail = `${stage.done} / ${stage.total}`;
      if (stage.eta_s !== null && stage.eta_s !== undefined) detail += ` · ${fmtSeconds(stage.eta_s)} left`;
    } else if (stage.status === "done") {
      detail = stage.seconds !== null && stage.seconds !== undefined ? fmtSeconds(stage.seconds) : "done";
    } else {
      detail = stage.status;
    }
    return h(
      "li",
      { class: `stage stage-${stage.status}`, dataset: { stage: stage.name, status: stage.status } },
      h("span", { class: "stage-name" }, STAGE_LABELS[stage.name] || stage.name),
      h(
        "span",
        { class: "bar", role: "progressbar", "aria-valuemin": 0, "aria-valuemax": 100, "aria-valuenow": pct.toFixed(0) },
        h("span", { class: "fill", style: { width: `${pct}%` } }),
      ),
      h("span", { class: "stage-detail" }, detail),
    );
  }

  function renderRunPanel() {
    const run = latestRun();
    if (!run) {
      replace(els.run, h("h2", {}, "Run"), h("p", { class: "muted" }, "No run yet. Press “Run pipeline” to label the dataset."));
      return;
    }
    const pr = run.progress;
    const status = pr.status;
    const eta = pr.eta_s !== null && pr.eta_s !== undefined ? ` · about ${fmtSeconds(pr.eta_s)} left` : "";
    const dur = duration(run);
    const head = h(
      "div",
      { class: "run-head" },
      h("h2", {}, `Run ${run.number}`),
      h("span", { id: "run-status", class: `chip status-${status}`, dataset: { status } }, status),
      h("span", { class: "muted", id: "run-percent" }, `${pr.percent.toFixed(0)} %${ACTIVE.has(status) ? eta : ""}`),
      dur !== null && TERMINAL.has(status) ? h("span", { class: "muted" }, `in ${fmtSeconds(dur)}`) : null,
      h("span", { class: "spacer" }),
      ACTIVE.has(status)
        ? h("button", { class: "btn small", id: "cancel-button", onclick: () => runAction(run, "cancel") }, "Cancel")
        : null,
      run.resumable
        ? h("button", { class: "btn small", id: "resume-button", onclick: () => runAction(run, "resume") }, "Resume")
        : null,
    );
    const overall = h(
      "div",
      { class: "bar overall", role: "progressbar", "aria-valuenow": pr.percent.toFixed(0) },
      h("span", { class: `fill status-${status}`, style: { width: `${pr.percent}%` } }),
    );
    replace(
      els.run,
      head,
      overall,
      h("ol", { class: "stages" }, pr.stages.map(stageRow)),
      pr.error ? h("p", { class: "error run-error", role: "alert" }, pr.error) : null,
    );
  }

  // ----------------------------------------------------------------------------------- run history
  function rowsOf(runs) {
    const rows = [];
    for (const r of runs) {
      const table = r.summary && r.summary[state.protocol];
      if (table) for (const k of Object.keys(table)) if (!rows.includes(k)) rows.push(k);
    }
    return rows;
  }

  function defaultCompare() {
    if (state.compareTouched) return;
    state.compare = new Set(state.runs.filter((r) => r.has_metrics).slice(0, 2).map((r) => r.id));
  }

  function runActions(run) {
    const out = [];
    if (run.has_export) {
      out.push(
        h("a", { class: "btn small", href: url(`/runs/${run.id}/export.zip`), download: "", dataset: { action: "zip" } }, "Labels .zip"),
        h(
          "button",
          {
            class: "btn small ghost",
            dataset: { action: "predictions" },
            title: "Write the .label files into the dataset's predictions/ folder",
            onclick: async () => {
              try {
                const res = await post(`/runs/${run.id}/export`, {});
                toast(`Wrote ${res.files} files to ${res.path}`);
              } catch (err) {
                toast(err.message, "error");
              }
            },
          },
          "→ predictions/",
        ),
      );
    }
    if (run.resumable) out.push(h("button", { class: "btn small", onclick: () => runAction(run, "resume") }, "Resume"));
    out.push(
      h(
        "button",
        {
          class: "btn small ghost",
          onclick: () => {
            if (state.openLogs.has(run.id)) state.openLogs.delete(run.id);
            else state.openLogs.add(run.id);
            renderRuns();
          },
        },
        state.openLogs.has(run.id) ? "Hide log" : "Log",
      ),
    );
    return out;
  }

  function renderRuns() {
    defaultCompare();
    const runs = state.runs;
    const rows = rowsOf(runs);
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
      h(
        "tbody",
        {},
        runs.map((run) => {
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
                  await renderCompare();
                },
              }),
            ),
            h("td", {}, `#${run.number}`),
            h("td", {}, statusChip(run.status)),
            h("td", { class: "muted" }, fmtTime(run.started_at || run.created_at)),
            h("td", { class: "muted" }, dur !== null && TERMINAL.has(run.status) ? fmtSeconds(dur) : ACTIVE.has(run.status) ? "…" : ""),
            rows.map((r) => h("td", { class: "num" }, fmtPct(miou(run, r, state.protocol)))),
            h("td", { class: "run-actions" }, runActions(run)),
          );
          const out = [tr];
          if (run.error && !ACTIVE.has(run.status)) {
            out.push(h("tr", { class: "sub" }, h("td", {}), h("td", { colspan: 5 + rows.length, class: "error small" }, run.error)));
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
        }),
      ),
    );
    replace(
      els.runs,
      h("div", { class: "card-head" }, h("h2", {}, "Run history"), h("span", { class: "muted small" }, "mIoU in %, camera-view protocol unless chosen below")),
      runs.length ? h("div", { class: "table-wrap" }, table) : h("p", { class: "muted" }, "No runs yet."),
    );
  }

  // -------------------------------------------------------------------------------------- compare
  async function metricsOf(runId) {
    if (!state.metrics.has(runId)) state.metrics.set(runId, await get(`/runs/${runId}/metrics`));
    return state.metrics.get(runId);
  }

  async function renderCompare() {
    const runs = state.runs.filter((r) => state.compare.has(r.id)).reverse();
    if (!runs.length) {
      replace(els.compare, h("h2", {}, "Metrics"), h("p", { class: "muted" }, "Finished runs on data with ground truth show their metrics here; tick runs in the history to compare them."));
      return;
    }
    let all;
    try {
      all = await Promise.all(runs.map((r) => metricsOf(r.id)));
    } catch (err) {
      replace(els.compare, h("h2", {}, "Metrics"), h("p", { class: "error" }, err.message));
      return;
    }
    const protocols = Object.keys(all[0].metrics.protocols);
    if (!protocols.includes(state.protocol)) state.protocol = protocols[0];
    const rowNames = [];
    for (const m of all) for (const r of m.metrics.rows.length ? m.metrics.rows : Object.keys(m.metrics.protocols[state.protocol])) if (!rowNames.includes(r)) rowNames.push(r);
    if (!rowNames.includes(state.row)) state.row = rowNames.includes("voxel") ? "voxel" : rowNames[rowNames.length - 1];

    const protoSel = h(
      "select",
      { id: "protocol-select", onchange: (e) => { state.protocol = e.target.value; renderRuns(); renderCompare(); } },
      protocols.map((p) => h("option", { value: p, selected: p === state.protocol }, p === "camera" ? "camera view (paper)" : "all points")),
    );
    const rowSel = h(
      "select",
      { id: "row-select", onchange: (e) => { state.row = e.target.value; renderCompare(); } },
      rowNames.map((r) => h("option", { value: r, selected: r === state.row }, r)),
    );

    const metricsTable = h(
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
              h("td", {}, j === 0 ? h("span", { class: "run-dot", style: { background: RUN_COLORS[i % RUN_COLORS.length] } }) : null, j === 0 ? `#${run.number}` : ""),
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

    const colorOf = new Map(state.classes.map((c) => [c.name, c.hex]));
    const names = all[all.length - 1].class_names;
    const classRows = names.map((n) => ({ name: n, color: colorOf.get(n) || "#999999" }));
    const series = runs.map((run, i) => {
      const row = (all[i].metrics.protocols[state.protocol] || {})[state.row];
      return { label: `run ${run.number}`, iou: row ? row.iou : {} };
    });
    const legend = h(
      "div",
      { class: "legend" },
      runs.map((run, i) => h("span", {}, h("span", { class: "run-dot", style: { background: RUN_COLORS[i % RUN_COLORS.length] } }), `run ${run.number}`)),
    );
    replace(
      els.compare,
      h("div", { class: "card-head" }, h("h2", {}, "Metrics"), h("div", { class: "row" }, h("label", { class: "inline" }, "Protocol ", protoSel), h("label", { class: "inline" }, "Chart ", rowSel))),
      h("div", { class: "table-wrap" }, metricsTable),
      h("h3", { class: "chart-title" }, `Per-class IoU (%) · ${state.row} labels`),
      legend,
      h("div", { id: "iou-chart" }, iouChart(series, classRows)),
    );
  }

  // -------------------------------------------------------------------------------------- classes
  async function classCall(fn) {
    const status = els.classes.querySelector(".editor-status");
    try {
      const res = await fn();
      state.classes = res.data;
      renderClasses();
      const s2 = els.classes.querySelector(".editor-status");
      s2.textContent = "Saved";
      s2.className = "editor-status ok";
      return true;
    } catch (err) {
      if (status) {
        status.textContent = err.message;
        status.className = "editor-status error";
      }
      return false;
    }
  }

  function classRow(c) {
    const base = `/projects/${projectId}/classes/${enc(c.name)}`;
    const color = h("input", {
      type: "color",
      class: "cls-color",
      value: c.hex,
      title: "Color",
      "aria-label": `Color of ${c.name}`,
      onchange: (e) => classCall(() => patch(base, { color: e.target.value })),
    });
    const name = h("input", {
      class: "cls-name",
      value: c.name,
      "aria-label": "Class name",
      maxlength: 64,
      onchange: (e) => {
        const v = e.target.value.trim();
        if (v && v !== c.name) classCall(() => patch(base, { name: v }));
        else e.target.value = c.name;
      },
    });
    const exportId = h("input", {
      class: "cls-export",
      type: "number",
      min: 1,
      max: 65535,
      value: String(c.export_id),
      title: "Export id written to .label files",
      "aria-label": `Export id of ${c.name}`,
      onchange: (e) => classCall(() => patch(base, { export_id: Number(e.target.value) })),
    });
    const remove = h(
      "button",
      {
        class: "icon cls-delete",
        title: `Remove class ${c.name}`,
        "aria-label": `Remove class ${c.name}`,
        onclick: () => {
          if (window.confirm(`Remove class “${c.name}”?`)) classCall(() => del(base));
        },
      },
      "×",
    );
    const chips = c.prompts.map((p, i) =>
      h(
        "span",
        { class: "prompt", dataset: { index: String(i) } },
        h("span", { class: "prompt-text" }, p),
        h(
          "button",
          {
            class: "prompt-remove",
            title: `Remove prompt ${p}`,
            "aria-label": `Remove prompt ${p}`,
            onclick: () => classCall(() => del(`${base}/prompts/${i}`)),
          },
          "×",
        ),
      ),
    );
    const add = h("input", {
      class: "prompt-add",
      placeholder: "+ prompt",
      "aria-label": `Add a prompt to ${c.name}`,
      maxlength: 200,
      onkeydown: (e) => {
        if (e.key !== "Enter") return;
        e.preventDefault();
        const v = e.target.value.trim();
        if (v) classCall(() => post(`${base}/prompts`, { prompt: v }));
      },
    });
    return h(
      "li",
      { class: "class-row", dataset: { class: c.name } },
      h("div", { class: "class-line" }, color, name, exportId, remove),
      h("div", { class: "prompts" }, chips, add),
    );
  }

  function addClassForm() {
    const name = h("input", { placeholder: "new class", maxlength: 64, id: "new-class-name", "aria-label": "New class name" });
    const color = h("input", { type: "color", value: "#888888", "aria-label": "New class color" });
    const nextId = Math.max(0, ...state.classes.map((c) => c.export_id)) + 1;
    const exportId = h("input", { type: "number", min: 1, max: 65535, value: String(Math.min(nextId, 65535)), class: "cls-export", "aria-label": "New class export id" });
    const prompts = h("input", { placeholder: "prompts, comma separated", id: "new-class-prompts", "aria-label": "New class prompts" });
    return h(
      "form",
      {
        class: "add-class",
        onsubmit: async (e) => {
          e.preventDefault();
          const list = prompts.value.split(",").map((p) => p.trim()).filter(Boolean);
          const n = name.value.trim();
          if (!n) return;
          await classCall(() =>
            post(`/projects/${projectId}/classes`, { name: n, color: color.value, export_id: Number(exportId.value), prompts: list.length ? list : [n] }),
          );
        },
      },
      h("div", { class: "class-line" }, color, name, exportId, h("button", { class: "btn small", type: "submit" }, "Add")),
      prompts,
    );
  }

  function renderClasses() {
    replace(
      els.classes,
      h("div", { class: "card-head" }, h("h2", {}, "Classes & prompts"), h("span", { class: "muted small" }, `${state.classes.length} classes`)),
      h("p", { class: "muted small" }, "Color · name · export id. Enter adds a prompt; the next run uses the edits."),
      h("p", { class: "editor-status", role: "status" }),
      h("ol", { class: "class-list" }, state.classes.map(classRow)),
      addClassForm(),
    );
  }

  // ------------------------------------------------------------------------------------- parameters
  function renderParams() {
    const form = state.project.form;
    const inputs = {};
    const error = h("p", { class: "error", role: "alert" });
    const fields = PARAMS.map((p) => {
      let input;
      if (p.type === "select") {
        input = h("select", { name: p.name }, p.options.map(([v, label]) => h("option", { value: v, selected: form[p.name] === v }, label)));
      } else if (p.type === "checkbox") {
        input = h("input", { type: "checkbox", name: p.name, checked: Boolean(form[p.name]) });
      } else {
        input = h("input", { type: "number", name: p.name, step: p.step, min: p.min, max: p.max, value: String(form[p.name]) });
      }
      inputs[p.name] = input;
      return h("label", { class: `param ${p.type}`, dataset: { param: p.name } }, h("span", {}, p.label), input);
    });
    const save = h("button", { class: "btn small primary", type: "submit", id: "save-params" }, "Save parameters");
    replace(
      els.params,
      h("h2", {}, "Parameters"),
      h(
        "form",
        {
          class: "params-grid",
          novalidate: true, // the server checks every value and names the field in its answer
          onsubmit: async (e) => {
            e.preventDefault();
            error.textContent = "";
            for (const el of Object.values(inputs)) el.classList.remove("invalid");
            const values = {};
            for (const p of PARAMS) {
              const el = inputs[p.name];
              values[p.name] = p.type === "checkbox" ? el.checked : p.type === "select" ? el.value : Number(el.value);
            }
            try {
              state.project = await patch(`/projects/${projectId}`, { form: values });
              toast("Parameters saved");
              renderParams();
            } catch (err) {
              error.textContent = err.message;
              const f = err instanceof ApiError ? err.field() : null;
              if (f && inputs[f]) inputs[f].classList.add("invalid");
            }
          },
        },
        fields,
        error,
        h("div", { class: "row end" }, save),
      ),
    );
  }

  // ------------------------------------------------------------------------------------------ mount
  try {
    await loadAll();
  } catch (err) {
    replace(root, h("section", { class: "card" }, h("a", { href: "#/", class: "back" }, "← Projects"), h("p", { class: "error" }, err.message)));
    return () => {};
  }
  replace(
    root,
    els.head,
    h(
      "div",
      { class: "layout" },
      h("div", { class: "main-col" }, els.run, els.compare, els.runs),
      h("aside", { class: "side-col" }, els.classes, els.params),
    ),
  );
  renderHead();
  renderRunPanel();
  renderRuns();
  renderClasses();
  renderParams();
  await renderCompare();
  follow(state.runs.find((r) => ACTIVE.has(r.status)));

  return () => {
    disposed = true;
    if (state.stream) state.stream.close();
  };
}

