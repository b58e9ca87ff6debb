// The link to the 3D review viewer: starts (or reuses) the project's viewer on its latest finished run.

import { post, url } from "../api.js";
import { h } from "../dom.js";

/** The "Open 3D viewer" button, or null when the server has no viewer. */
export function viewerButton(ctx) {
  const { state, projectId, toast } = ctx;
  if (!(state.health && state.health.viewer)) return null;
  const lastDone = state.runs.find((r) => r.status === "done");
  return h(
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
  );
}
