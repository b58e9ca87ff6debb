// The link to the 3D review viewer: opens a new viewer tab (its own scan, camera, selection and focus) on
// the project's latest finished run.

import { post, url } from "../api.js";
import { h } from "../dom.js";
import { reviewerName } from "./reviewers.js";

/** The sequence picker beside the button, for a project of several sequences (null otherwise): the
 * viewer shows one sequence at a time. */
function sequencePicker(ctx) {
  const { state } = ctx;
  const seqs = state.project.sequences || [];
  if (seqs.length < 2) return null;
  if (!seqs.some((s) => s.name === state.viewerSequence)) state.viewerSequence = seqs[0].name;
  return h(
    "label",
    { class: "inline viewer-sequence" },
    "Sequence ",
    h(
      "select",
      {
        id: "viewer-sequence",
        onchange: (e) => {
          state.viewerSequence = e.target.value;
          // The review progress and the corrections shown are the picked sequence's.
          if (ctx.render.review) ctx.render.review();
          if (ctx.render.corrections) ctx.render.corrections();
        },
      },
      seqs.map((s) => h("option", { value: s.name, selected: s.name === state.viewerSequence }, s.name)),
    ),
  );
}

/** Open the viewer on the latest finished run (of the picked sequence) in a new tab; `then(v)` runs once
 * the server has it loaded, before the tab navigates (e.g. to jump to a correction). False without a
 * finished run. */
export async function openViewer(ctx, then = null) {
  const { state, projectId, toast } = ctx;
  const lastDone = state.runs.find((r) => r.status === "done");
  if (!lastDone) return false;
  // Opened before any await: a window opened later is no longer the click's and gets blocked.
  const win = window.open("about:blank", "_blank");
  try {
    const body = { run_id: lastDone.id };
    if ((state.project.sequences || []).length > 1) body.sequence = state.viewerSequence;
    // The tab stores this browser's reviewer name with its corrections and review marks.
    if (reviewerName()) body.reviewer = reviewerName();
    const v = await post(`/projects/${projectId}/viewer`, body);
    if (then) await then(v);
    if (win) win.location = url(v.url);
  } catch (err) {
    if (win) win.close();
    toast(err.message, "error");
  }
  return true;
}

/** The "Open 3D viewer" button (with the sequence picker of a project of several sequences), or null when
 * the server has no viewer. */
export function viewerButton(ctx) {
  const { state } = ctx;
  if (!(state.health && state.health.viewer)) return null;
  const lastDone = state.runs.find((r) => r.status === "done");
  const picker = sequencePicker(ctx);
  const button = h(
    "button",
    {
      class: "btn",
      id: "viewer-button",
      disabled: !lastDone,
      title: lastDone ? `Review run ${lastDone.number} in 3D` : "Needs a finished run",
      onclick: () => openViewer(ctx),
    },
    "Open 3D viewer",
  );
  return picker ? h("span", { class: "viewer-open" }, button, picker) : button;
}
