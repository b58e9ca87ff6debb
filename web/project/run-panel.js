// The latest run: status, overall progress with ETA, one progress bar per stage, cancel / resume, and for a
// run that failed on a project setting (run.fix_setting) a new run with the project's current settings:
// Resume keeps the run's own settings, so after that setting is changed it would fail the same way.

import { duration, fmtSeconds, h, replace } from "../dom.js";
import { latestRun } from "./context.js";

/** The sequence and stage of a progress stage name: the server names a run's stages "<sequence>/<stage>"
 * ("*" for the 3D-CN rounds, trained on every sequence at once); runs stored before runs had sequences
 * have bare stage names. */
function splitStage(name) {
  const cut = name.indexOf("/");
  return cut < 0 ? [null, name] : [name.slice(0, cut), name.slice(cut + 1)];
}

/** A stage's label: "Fuse", or in a run of several sequences "01 · Fuse" ("all · 3D-CN" for the 3D-CN
 * rounds). */
function stageLabel(ctx, name, several) {
  const [seq, base] = splitStage(name);
  const info = ctx.stages.get(base);
  const label = info ? info.label : base;
  return { info, text: seq === null || !several ? label : `${seq === "*" ? "all" : seq} · ${label}` };
}

function stageRow(ctx, stage, several) {
  const { info, text } = stageLabel(ctx, stage.name, several);
  const pct = Math.max(0, Math.min(100, stage.percent));
  let detail = "";
  if (stage.status === "running") {
    detail = `${stage.done} / ${stage.total}`;
    if (stage.eta_s !== null && stage.eta_s !== undefined) detail += ` · ${fmtSeconds(stage.eta_s)} left`;
  } else if (stage.status === "done") {
    detail = stage.seconds !== null && stage.seconds !== undefined ? fmtSeconds(stage.seconds) : "done";
  } else if (stage.status === "skipped") {
    detail = stage.note ? `skipped (${stage.note})` : "skipped";
  } else {
    detail = stage.status;
  }
  return h(
    "li",
    { class: `stage stage-${stage.status}`, dataset: { stage: stage.name, status: stage.status } },
    h("span", { class: "stage-name", title: info ? info.description : null }, text),
    h(
      "span",
      { class: "bar", role: "progressbar", "aria-valuemin": 0, "aria-valuemax": 100, "aria-valuenow": pct.toFixed(0) },
      h("span", { class: "fill", style: { width: `${pct}%` } }),
    ),
    h("span", { class: "stage-detail" }, detail),
  );
}

/** What Resume does, on every Resume button. */
export const RESUME_TITLE =
  "Continue this run where it stopped, with the settings it was started with (changes made since are not used)";

export function renderRunPanel(ctx) {
  const el = ctx.els.run;
  const run = latestRun(ctx);
  if (!run) {
    replace(el, h("h2", {}, "Run"), h("p", { class: "muted" }, "No run yet. Press “Run pipeline” to label the dataset."));
    return;
  }
  const pr = run.progress;
  const status = pr.status;
  const sequences = new Set(pr.stages.map((st) => splitStage(st.name)[0]).filter((seq) => seq !== null && seq !== "*"));
  const several = sequences.size > 1;
  const active = ctx.active.has(status);
  const eta = pr.eta_s !== null && pr.eta_s !== undefined ? ` · about ${fmtSeconds(pr.eta_s)} left` : "";
  const dur = duration(run);
  const fix = status === "failed" ? run.fix_setting : null;
  const head = h(
    "div",
    { class: "run-head" },
    h("h2", {}, `Run ${run.number}`),
    h("span", { id: "run-status", class: `chip status-${status}`, dataset: { status } }, status),
    h("span", { class: "muted", id: "run-percent" }, `${pr.percent.toFixed(0)} %${active ? eta : ""}`),
    dur !== null && ctx.terminal.has(status) ? h("span", { class: "muted" }, `in ${fmtSeconds(dur)}`) : null,
    h("span", { class: "spacer" }),
    active
      ? h("button", { class: "btn small", id: "cancel-button", onclick: () => ctx.actions.runAction(run, "cancel") }, "Cancel")
      : null,
    fix
      ? h(
        "button",
        {
          class: "btn small primary",
          id: "run-again-button",
          title: "Start a new run with the project's current settings (this run's own settings stay as they were)",
          onclick: ctx.actions.startRun,
        },
        "Run again with the new settings",
      )
      : null,
    run.resumable
      ? h("button", { class: "btn small", id: "resume-button", title: RESUME_TITLE, onclick: () => ctx.actions.runAction(run, "resume") }, "Resume")
      : null,
  );
  const overall = h(
    "div",
    { class: "bar overall", role: "progressbar", "aria-valuenow": pr.percent.toFixed(0) },
    h("span", { class: `fill status-${status}`, style: { width: `${pr.percent}%` } }),
  );
  replace(
    el,
    head,
    overall,
    h("ol", { class: "stages" }, pr.stages.map((stage) => stageRow(ctx, stage, several))),
    pr.error ? h("p", { class: "error run-error", role: "alert" }, pr.error) : null,
    fix
      ? h(
        "p",
        { class: "run-fix", id: "run-fix" },
        `The fix is a setting (${fix}). Resume keeps this run's own settings, so it would fail the same way: `,
        `change ${fix}, then press “Run again with the new settings”.`,
      )
      : null,
    pr.warnings && pr.warnings.length
      ? h("ul", { class: "run-warnings", "aria-label": "Warnings" }, pr.warnings.map((w) => h("li", {}, w)))
      : null,
  );
}
