// The dataset check (GET /datasets and a project's dataset.check; leap_core/pipeline/preflight.py, its
// fixes worded in app/advice.py): what the pipeline can do with a dataset, each problem with its fix in
// the app's words. Shown under the dataset picker of the create-project form and as a card on the project
// page.

import { h, replace } from "./dom.js";

const SEVERITY_ORDER = { blocker: 0, warning: 1, info: 2 };

/** The findings worth showing (blockers and warnings; facts without a fix stay in the details). */
function problems(check) {
  return check.findings
    .filter((f) => f.severity !== "info")
    .sort((a, b) => SEVERITY_ORDER[a.severity] - SEVERITY_ORDER[b.severity]);
}

function findingItem(f) {
  return h(
    "li",
    { class: `check-finding check-${f.severity}`, dataset: { code: f.code, severity: f.severity } },
    h("span", { class: "check-message" }, f.message),
    f.fix ? h("span", { class: "check-fix" }, ` Fix: ${f.fix}`) : null,
  );
}

function stageList(check) {
  return h(
    "ul",
    { class: "check-stages small" },
    check.stages.map((s) =>
      h(
        "li",
        { class: `check-stage check-stage-${s.state}`, dataset: { stage: s.name, state: s.state } },
        h("span", { class: "stage-name" }, s.label),
        " ",
        s.state === "runs" ? "runs" : s.state === "skipped" ? `skipped (${s.reason})` : `cannot run (${s.reason})`,
      ),
    ),
  );
}

function facts(check) {
  const poses = { file: "poses.txt", estimated: "estimated poses", missing: "no poses", invalid: "unreadable poses", "will-estimate": "poses estimated before the 3D stages" }[check.poses.source];
  const cameras = check.cameras && check.cameras.length > 1 ? ` · ${check.cameras.length} cameras: ${check.cameras.map((c) => `${c.name} (${c.images.present} images)`).join(", ")}` : "";
  return `${check.frames} frames · ${check.images.present} with a camera image · ${poses} · ground truth: ${check.ground_truth.kind} · 2D ground truth: ${check.gt2d.kind}${cameras}`;
}

/** A compact summary for the create-project form: the verdict and the problems with their fixes. */
export function checkSummary(check) {
  if (!check) return null;
  const list = problems(check);
  return h(
    "div",
    { class: `dataset-check verdict-${check.verdict}`, id: "new-dataset-check", dataset: { verdict: check.verdict } },
    h("p", { class: "small" }, h("strong", {}, check.verdict === "full" ? "✓ " : "⚠ "), check.summary, " · ", facts(check)),
    list.length ? h("ul", { class: "check-findings small" }, list.map(findingItem)) : null,
  );
}

/** Whether a check has anything to say (a stage that cannot run, or a problem with a fix). */
function worthShowing(check) {
  return check.verdict !== "full" || problems(check).length > 0;
}

function calibFact(check) {
  return !check.calib.present ? "no calib.txt" : check.calib.valid ? "calibration" : "unreadable calib.txt";
}

/** One sequence's part of the card: its facts, problems and stages. */
function sequenceCheck(name, check) {
  const list = problems(check);
  return h(
    "li",
    { class: `sequence-check verdict-${check.verdict}`, dataset: { sequence: name, verdict: check.verdict } },
    h("p", { class: "small" }, h("strong", {}, name), ` · ${check.summary} · ${calibFact(check)} · ${facts(check)}`),
    list.length ? h("ul", { class: "check-findings" }, list.map(findingItem)) : null,
    worthShowing(check) ? h("details", {}, h("summary", { class: "small" }, "Stages"), stageList(check)) : null,
  );
}

/** The project page's "Dataset check" card (hidden when every stage can run and nothing needs a word).
 * A project of several sequences lists each sequence's check (frames, calibration, images, poses, ground
 * truth, problems with their fixes) as soon as one of them needs a word. */
export function renderDatasetCheck(el, project) {
  const seqs = (project.sequences || []).filter((s) => s.dataset && s.dataset.check);
  if (seqs.length > 1) {
    const shown = seqs.some((s) => worthShowing(s.dataset.check));
    el.hidden = !shown;
    if (!shown) {
      replace(el);
      return;
    }
    replace(
      el,
      h("h2", {}, "Dataset check"),
      h("ul", { class: "sequence-checks", id: "sequence-checks" }, seqs.map((s) => sequenceCheck(s.name, s.dataset.check))),
    );
    return;
  }
  const check = project.dataset && project.dataset.check;
  const list = check ? problems(check) : [];
  if (!check || (check.verdict === "full" && !list.length)) {
    el.hidden = true;
    replace(el);
    return;
  }
  el.hidden = false;
  replace(
    el,
    h("h2", {}, "Dataset check"),
    h("p", { class: "muted small" }, `${check.summary} · ${facts(check)}`),
    h("ul", { class: "check-findings" }, list.map(findingItem)),
    h("details", {}, h("summary", { class: "small" }, "Stages"), stageList(check)),
  );
}
