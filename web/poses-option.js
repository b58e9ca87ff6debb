// "Estimate poses (KISS-ICP)": the project option for datasets recorded without poses.txt. A run of such a
// project estimates LiDAR odometry into the work folder first (cached per dataset); the dataset is never
// written. Kept in its own module so the create form and the project page share one wording.

import { patch } from "./api.js";
import { h } from "./dom.js";

const LABEL = "Estimate poses (KISS-ICP)";
const HELP =
  "When the dataset has no poses.txt, each run first estimates the poses with KISS-ICP LiDAR odometry, " +
  "into the work folder (the dataset is not written). A dataset with its own poses.txt keeps using them.";

/** The create form's checkbox: `{ element, checked() }`. */
export function posesOption() {
  const box = h("input", { type: "checkbox", id: "new-estimate-poses", name: "estimate_poses" });
  const element = h(
    "label",
    { class: "poses-option field", title: HELP },
    box,
    h("span", {}, LABEL),
    h("span", { class: "muted small poses-option-note" }, "for sequences recorded without poses.txt"),
  );
  return { element, checked: () => box.checked };
}

/** The project page's switch of the same option (saved at once). */
export function posesToggle(ctx) {
  const { state, projectId, toast } = ctx;
  const box = h("input", { type: "checkbox", id: "estimate-poses", checked: Boolean(state.project.estimate_poses) });
  box.addEventListener("change", async () => {
    box.disabled = true;
    try {
      state.project = await patch(`/projects/${projectId}`, { estimate_poses: box.checked });
      toast(box.checked ? "Runs will estimate poses when the dataset has none" : "Runs use the dataset's poses only");
    } catch (err) {
      box.checked = !box.checked;
      toast(err.message, "error");
    } finally {
      box.disabled = false;
    }
  });
  return h("label", { class: "poses-option small", title: HELP }, box, h("span", {}, LABEL));
}
