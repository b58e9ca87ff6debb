// The next run, before it starts: which stages it recomputes and which it reuses from the latest finished run
// (GET /projects/{id}/runs/preview compares the fingerprints it would have with that run's), what changed
// since that run, and a note to keep with it. The plan is re-rendered after every class, prompt or parameter
// edit; the note field is built once and never replaced, so a preview that lands while the user types takes
// neither the focus nor the keystrokes.

import { get } from "../api.js";
import { h, replace } from "../dom.js";

let seq = 0; // answers of older requests are dropped when edits come faster than the server answers

function changeList(changes, id) {
  if (!changes.length) return h("p", { class: "muted small" }, "No changes since that run.");
  return h(
    "ul",
    { class: "change-list", id },
    changes.map((c) =>
      h(
        "li",
        { class: c.ignored ? "ignored" : "", dataset: { kind: c.kind, subject: c.subject } },
        c.text,
        c.ignored ? h("span", { class: "muted small" }, ` — no effect: ${c.ignored}`) : null,
      ),
    ),
  );
}

export { changeList };

/** The card's two parts: the plan (replaced by each render) and the note field (built once). */
function parts(ctx) {
  const { state } = ctx;
  if (!ctx.els.nextPlan) {
    const note = h("input", {
      id: "run-note",
      maxlength: 500,
      placeholder: "note for the next run (optional)",
      "aria-label": "Note for the next run",
      value: state.runNote || "",
      oninput: (e) => (state.runNote = e.target.value),
    });
    ctx.els.nextNote = note;
    ctx.els.nextPlan = h("div", { class: "next-plan" }, h("h2", {}, "Next run"));
    replace(ctx.els.next, ctx.els.nextPlan, h("label", { class: "run-note" }, h("span", { class: "muted small" }, "Note"), note));
  }
  return ctx.els.nextPlan;
}

export async function renderNextRun(ctx) {
  const { state, projectId } = ctx;
  const el = parts(ctx);
  // A started run took the note: the field empties (it is never rebuilt, so it is cleared here).
  if (!state.runNote && ctx.els.nextNote.value) ctx.els.nextNote.value = "";
  const mine = ++seq;
  let preview;
  try {
    preview = await get(`/projects/${projectId}/runs/preview`);
  } catch (err) {
    if (mine === seq) replace(el, h("h2", {}, "Next run"), h("p", { class: "error" }, err.message));
    return;
  }
  if (mine !== seq) return;
  const recompute = preview.stages.filter((s) => s.action === "recompute");
  const reuse = preview.stages.filter((s) => s.action === "reuse");
  const summary = !preview.base_run
    ? preview.stale
      ? `The sequences changed since run ${preview.stale.run_number}: the next run computes every stage.`
      : "Nothing to reuse: the next run computes every stage."
    : recompute.length === 0
      ? `Nothing changed since run ${preview.base_run.number}: the next run reuses every stage.`
      : `Against run ${preview.base_run.number}, the next run recomputes ${recompute.length} of ${preview.stages.length} stages.`;
  replace(
    el,
    h("div", { class: "card-head" }, h("h2", {}, "Next run"), h("span", { class: "muted small", id: "next-summary" }, summary)),
    preview.problem ? h("p", { class: "error small" }, preview.problem) : null,
    h(
      "ol",
      { class: "plan", id: "recompute-plan" },
      preview.stages.map((s) =>
        h(
          "li",
          { class: `plan-stage plan-${s.action}`, dataset: { stage: s.name, action: s.action }, title: s.reason },
          h("span", { class: "plan-name" }, s.label),
          h("span", { class: "plan-action" }, s.action === "recompute" ? "recomputes" : s.action === "reuse" ? "reused" : "off"),
          s.action === "recompute" ? h("span", { class: "plan-reason muted small" }, s.reason) : null,
        ),
      ),
    ),
    reuse.length && recompute.length ? h("p", { class: "muted small" }, `Reused: ${reuse.map((s) => s.label).join(", ")}.`) : null,
    preview.base_run ? h("h3", { class: "small" }, `Changes since run ${preview.base_run.number}`) : null,
    preview.base_run ? changeList(preview.changes, "pending-changes") : null,
  );
}
