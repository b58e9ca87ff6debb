// The project's sequences (POST /projects/{id}/sequences, DELETE /projects/{id}/sequences/{name}): each
// with its folder, frames and ground truth; a folder to add (confined and checked by the server as at
// creation; the data roots' sequence folders are offered) and a remove button per sequence (confirmed;
// nothing on disk is deleted). While a run is queued or running, or for the last sequence, the server
// refuses and the buttons are off. After an edit the latest run describes other sequences: the server's
// `stale` note is shown until a run labels the current ones.

import { del, enc, get, post } from "../api.js";
import { h, replace } from "../dom.js";

let candidates = null; // GET /datasets, fetched once per page for the path field's suggestions

async function datasetOptions() {
  if (candidates === null) {
    try {
      candidates = (await get("/datasets")).data.map((d) => d.path);
    } catch (_) {
      candidates = [];
    }
  }
  return candidates;
}

/** After an edit: the answer is the whole project (every sequence with its dataset check). */
function applyProject(ctx, project) {
  ctx.state.project = project;
  ctx.render.head();
  ctx.render.sequences();
  ctx.render.check();
  ctx.render.next();
  ctx.render.review();
  if (ctx.render.corrections) ctx.render.corrections();
}

function sequenceItem(ctx, s, locked) {
  const { state, projectId, toast } = ctx;
  const last = state.project.sequences.length < 2;
  return h(
    "li",
    { class: "sequence-item", dataset: { sequence: s.name } },
    h(
      "span",
      { class: "sequence-text" },
      h("strong", {}, s.name),
      " ",
      h("code", {}, s.dataset.path),
      s.dataset.frames !== null ? ` · ${s.dataset.frames} frames` : " · missing",
      s.dataset.has_ground_truth ? " · ground truth" : "",
    ),
    h(
      "button",
      {
        class: "btn ghost small danger sequence-remove",
        dataset: { sequence: s.name },
        title: last ? "A project keeps one sequence at least" : locked || `Remove ${s.name} from the project`,
        disabled: last || Boolean(locked),
        onclick: async () => {
          const ok = window.confirm(
            `Remove sequence “${s.name}” from the project? Its folder, earlier runs and its corrections stay; the next run labels the other sequences.`,
          );
          if (!ok) return;
          try {
            applyProject(ctx, await del(`/projects/${projectId}/sequences/${enc(s.name)}`));
            toast(`Sequence ${s.name} removed`);
          } catch (err) {
            toast(err.message, "error");
          }
        },
      },
      "Remove",
    ),
  );
}

function addForm(ctx, locked) {
  const { projectId, toast } = ctx;
  const path = h("input", {
    id: "sequence-path",
    list: "sequence-path-options",
    placeholder: "sequence folder, e.g. …/sequences/01",
    "aria-label": "Folder of the sequence to add",
    maxlength: 4096,
  });
  const name = h("input", {
    id: "sequence-name",
    class: "narrow",
    placeholder: "name (folder's)",
    "aria-label": "Name of the sequence to add (default: the folder's name)",
    maxlength: 64,
  });
  const error = h("p", { class: "error small", id: "sequence-error", hidden: true });
  const options = h("datalist", { id: "sequence-path-options" });
  datasetOptions().then((paths) => {
    const have = new Set(ctx.state.project.sequences.map((s) => s.dataset.path));
    replace(options, paths.filter((p) => !have.has(p)).map((p) => h("option", { value: p })));
  });
  const button = h("button", { class: "btn small", id: "sequence-add", type: "submit", disabled: Boolean(locked), title: locked || "" }, "Add");
  return h(
    "form",
    {
      class: "sequence-add",
      onsubmit: async (e) => {
        e.preventDefault();
        const body = { path: path.value.trim() };
        if (name.value.trim()) body.name = name.value.trim();
        if (!body.path) return;
        button.disabled = true;
        try {
          const project = await post(`/projects/${projectId}/sequences`, body);
          applyProject(ctx, project);
          toast(`Sequence ${project.sequences[project.sequences.length - 1].name} added`);
        } catch (err) {
          error.hidden = false;
          replace(error, err.message);
          button.disabled = false;
        }
      },
    },
    h("div", { class: "row" }, path, name, button),
    options,
    error,
  );
}

export function renderSequences(ctx) {
  const p = ctx.state.project;
  const el = ctx.els.sequences;
  const active = p.active_run;
  const locked = active ? `Run ${active.number} is ${active.status}: sequences change once it ends` : null;
  const demo = p.dataset.kind === "demo";
  replace(
    el,
    h("div", { class: "card-head" }, h("h2", {}, "Sequences"), h("span", { class: "muted small" }, `${p.sequences.length}`)),
    h("ul", { class: "sequence-list", id: "sequence-list" }, p.sequences.map((s) => sequenceItem(ctx, s, locked || (demo ? "The demo project labels its one street" : null)))),
    p.stale ? h("p", { class: "stale-note small", id: "sequences-stale" }, p.stale.message) : null,
    demo ? h("p", { class: "muted small" }, "The demo project labels the generated street only; create a project on sequence folders to label several.") : addForm(ctx, locked),
  );
}
