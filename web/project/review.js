// Review progress of the project: how many regions of each review queue (ranked in the 3D viewer) are
// reviewed. Marks live in the project's database, so this shows without a running viewer.

import { get } from "../api.js";
import { h, replace } from "../dom.js";

const KIND_NAMES = { confidence: "lowest confidence", disagreement: "camera vs final disagreement" };

/** Mount the "Review progress" card after the run panel and fill it. */
export async function renderReview(ctx) {
  const { projectId, els } = ctx;
  let card = document.getElementById("review-progress");
  if (!card) {
    card = h("section", { class: "card", id: "review-progress" });
    els.run.after(card);
  }
  // A project of several sequences: the sequence picked beside "Open 3D viewer" (marks are per sequence).
  const seq = sequenceQuery(ctx);
  const title = h("h2", {}, seq ? `Review progress · ${ctx.state.viewerSequence}` : "Review progress");
  let data;
  try {
    data = (await get(`/projects/${projectId}/review${seq}`)).data;
  } catch (err) {
    replace(card, title, h("p", { class: "error" }, err.message));
    return;
  }
  const lines = data.length
    ? data.map((q) => {
        const skipped = q.skipped ? `, ${q.skipped} skipped` : "";
        return h(
          "p",
          { class: "review-line", "data-kind": q.kind },
          h("strong", {}, `${q.reviewed} / ${q.total} reviewed`),
          `${skipped} (${KIND_NAMES[q.kind] || q.kind} queue)`,
        );
      })
    : [h("p", { class: "muted" }, "No review queue ranked yet: open the 3D viewer and press Next region (N).")];
  replace(card, title, ...lines);
}

/** `?sequence=<name>` of the sequence picked beside "Open 3D viewer" in a project of several sequences,
 * else "" (the project's one sequence). */
export function sequenceQuery(ctx) {
  const seqs = ctx.state.project.sequences || [];
  const name = ctx.state.viewerSequence;
  return seqs.length > 1 && name ? `?sequence=${encodeURIComponent(name)}` : "";
}
