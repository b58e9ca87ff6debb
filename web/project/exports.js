// A finished run's exports: the .label files as a zip download, or written into the dataset's predictions/.

import { post, url } from "../api.js";
import { h } from "../dom.js";

/** The export actions of a run (none until the run has exported labels). */
export function exportActions(ctx, run) {
  if (!run.has_export) return [];
  return [
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
            ctx.toast(`Wrote ${res.files} files to ${res.path}`);
          } catch (err) {
            ctx.toast(err.message, "error");
          }
        },
      },
      "→ predictions/",
    ),
  ];
}
