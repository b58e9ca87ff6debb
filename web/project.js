// One project page: loads the project, its classes and runs and the pipeline description, mounts one
// panel module per card (project/*.js) and follows the live progress of the active run.
//
//   head.js       name, dataset, run / 3D viewer (viewer.js) / delete actions
//   run-panel.js  the latest run: per-stage progress, cancel, resume
//   history.js    run history (exports.js: the export dialog), compare check boxes, logs
//   compare.js    metrics of the compared runs: table and per-class IoU chart
//   sequences.js  the project's sequences: add a folder, remove one (confirmed), the "results stale" note
//   next-run.js   what the next run recomputes (and why), what changed since the latest run, its note
//   classes.js    classes & prompts editor (colours, ground-truth ids)
//   models.js     LiDAR-only models: train, their cards, label a sequence with one (mounted last)
//   params.js     pipeline parameters form (settings the chosen labeler or a switched-off stage ignores are
//                 greyed out with the reason)

import { get, post, url } from "./api.js";
import { h, replace } from "./dom.js";
import { pipelineInfo } from "./pipeline.js";
import { renderDatasetCheck } from "./dataset-check.js";
import { renderClasses } from "./project/classes.js";
import { renderCompare } from "./project/compare.js";
import { projectContext } from "./project/context.js";
import { renderHead } from "./project/head.js";
import { renderRuns } from "./project/history.js";
import { renderNextRun } from "./project/next-run.js";
import { renderParams } from "./project/params.js";
import { renderReview } from "./project/review.js";
import { renderReviewers } from "./project/reviewers.js";
import { renderRunPanel } from "./project/run-panel.js";
import { renderSequences } from "./project/sequences.js";

export async function renderProject(root, projectId, { toast }) {
  const state = {
    project: null,
    classes: [],
    nextColor: null,
    gtIds: null,
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
    check: h("section", { class: "card dataset-check-card", id: "dataset-check", hidden: true }),
    run: h("section", { class: "card", id: "run-panel" }),
    next: h("section", { class: "card", id: "next-run" }),
    runs: h("section", { class: "card", id: "runs" }),
    compare: h("section", { class: "card", id: "compare" }),
    sequences: h("section", { class: "card", id: "sequences" }),
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
    state.nextColor = classes.next_color;
    state.runs = runs.data;
    state.health = health;
  }

  async function refreshRuns() {
    const [project, runs] = await Promise.all([get(`/projects/${projectId}`), get(`/projects/${projectId}/runs`)]);
    state.project = project;
    state.runs = runs.data;
  }

  let pipeline;
  try {
    [pipeline] = await Promise.all([pipelineInfo(), loadAll()]);
  } catch (err) {
    replace(root, h("section", { class: "card" }, h("a", { href: "#/", class: "back" }, "← Projects"), h("p", { class: "error" }, err.message)));
    return () => {};
  }
  const ctx = projectContext({ projectId, state, els, pipeline, toast });
  ctx.render = {
    head: () => renderHead(ctx),
    sequences: () => renderSequences(ctx),
    run: () => renderRunPanel(ctx),
    next: () => renderNextRun(ctx),
    runs: () => renderRuns(ctx),
    compare: () => renderCompare(ctx),
    classes: () => renderClasses(ctx),
    params: () => renderParams(ctx),
    check: () => renderDatasetCheck(els.check, state.project),
    review: () => {
      renderReview(ctx);
      renderReviewers(ctx);
    },
  };

  // --------------------------------------------------------------------------------- live progress
  function follow(run) {
    if (!run || !ctx.active.has(run.status)) return;
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
          ctx.render.head();
          ctx.render.sequences();
        }
      }
      ctx.render.run();
    });
    es.addEventListener("end", async () => {
      es.close();
      state.stream = null;
      state.streamRun = null;
      if (disposed) return;
      await refreshRuns();
      const r = state.runs.find((x) => x.id === run.id);
      if (r) toast(`Run ${r.number} ${r.status}${r.error ? `: ${r.error}` : ""}`, r.status === "done" ? "info" : "error");
      ctx.render.head();
      ctx.render.sequences();
      ctx.render.run();
      ctx.render.runs();
      ctx.render.next();
      await ctx.render.compare();
    });
  }

  /** After a run was started, cancelled or resumed: show the new state and follow the run. */
  async function afterRunChange(runId, fallback) {
    await refreshRuns();
    ctx.render.head();
    ctx.render.sequences();
    ctx.render.run();
    ctx.render.runs();
    follow(state.runs.find((r) => r.id === runId) || fallback);
  }

  ctx.actions = {
    follow,
    startRun: async () => {
      try {
        const note = (state.runNote || "").trim();
        const run = await post(`/projects/${projectId}/runs`, note ? { note } : {});
        state.runNote = "";
        await afterRunChange(run.id, run);
        ctx.render.next();
      } catch (err) {
        toast(err.message, "error");
      }
    },
    runAction: async (run, action) => {
      try {
        await post(`/runs/${run.id}/${action}`, {});
        await afterRunChange(run.id, undefined);
      } catch (err) {
        toast(err.message, "error");
      }
    },
  };

  // ------------------------------------------------------------------------------------------ mount
  replace(
    root,
    els.head,
    h(
      "div",
      { class: "layout" },
      h("div", { class: "main-col" }, els.check, els.run, els.next, els.compare, els.runs),
      h("aside", { class: "side-col" }, els.sequences, els.classes, els.params),
    ),
  );
  ctx.render.head();
  ctx.render.sequences();
  ctx.render.check();
  ctx.render.run();
  ctx.render.runs();
  ctx.render.classes();
  ctx.render.params();
  ctx.render.next();
  renderReview(ctx);
  renderReviewers(ctx);
  await ctx.render.compare();
  follow(state.runs.find((r) => ctx.active.has(r.status)));
  import("./project/corrections.js").then((m) => m.mountCorrections(ctx));
  import("./project/models.js").then((m) => m.mountModels(ctx));

  return () => {
    disposed = true;
    if (state.stream) state.stream.close();
  };
}
