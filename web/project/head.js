// The page head: project name (renamable), dataset line (or the sequences' names), and the run / viewer /
// delete actions.

import { del, patch } from "../api.js";
import { h, replace } from "../dom.js";
import { posesToggle } from "../poses-option.js";
import { viewerButton } from "./viewer.js";

function renameButton(ctx, title) {
  const { state, projectId, toast } = ctx;
  const p = state.project;
  return h(
    "button",
    {
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
          ctx.render.head();
        };
        input.addEventListener("keydown", (e) => {
          if (e.key === "Enter") commit();
          if (e.key === "Escape") ctx.render.head();
        });
        input.addEventListener("blur", commit);
        title.replaceWith(input);
        input.focus();
      },
    },
    "Rename",
  );
}

function deleteButton(ctx) {
  const { state, projectId, toast } = ctx;
  const p = state.project;
  return h(
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
}

export function renderHead(ctx) {
  const p = ctx.state.project;
  const active = p.active_run;
  const title = h("h1", { id: "project-name" }, p.name);
  const runBtn = h(
    "button",
    { class: "btn primary", id: "run-button", disabled: Boolean(active), onclick: ctx.actions.startRun },
    active ? `Run ${active.number} ${active.status}…` : "▶ Run pipeline",
  );
  const ds = p.dataset;
  const several = p.sequences && p.sequences.length > 1;
  replace(
    ctx.els.head,
    h("a", { href: "#/", class: "back" }, "← Projects"),
    h("div", { class: "title-row" }, title, renameButton(ctx, title), p.is_demo ? h("span", { class: "chip demo" }, "demo") : null),
    several
      ? h(
          "p",
          { class: "muted dataset-line", id: "sequences-line" },
          // Each sequence's folder and frames are in the Sequences card (project/sequences.js).
          `${p.sequences.length} sequences: ${p.sequences.map((s) => s.name).join(", ")} · ${p.sequences.reduce((n, s) => n + (s.dataset.frames || 0), 0)} frames`,
        )
      : h(
          "p",
          { class: "muted dataset-line" },
          ds.kind === "demo" ? "Built-in demo sequence · " : "",
          h("code", {}, ds.path),
          ds.frames !== null ? ` · ${ds.frames} frames` : " · not generated yet",
          ds.has_ground_truth ? " · ground truth" : "",
        ),
    h("div", { class: "actions" }, runBtn, viewerButton(ctx), deleteButton(ctx)),
    posesToggle(ctx),
  );
}
