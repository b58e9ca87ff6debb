// Classes & prompts editor: colour, name and export id per class, prompt chips (Enter adds one), a form
// for a new class. Every edit is saved at once; the next run uses it.

import { del, enc, patch, post } from "../api.js";
import { h, replace } from "../dom.js";

/** Run one class-list request; on success show the new list, on failure its message. */
async function classCall(ctx, fn) {
  const status = ctx.els.classes.querySelector(".editor-status");
  try {
    const res = await fn();
    ctx.state.classes = res.data;
    renderClasses(ctx);
    const saved = ctx.els.classes.querySelector(".editor-status");
    saved.textContent = "Saved";
    saved.className = "editor-status ok";
    return true;
  } catch (err) {
    if (status) {
      status.textContent = err.message;
      status.className = "editor-status error";
    }
    return false;
  }
}

function classRow(ctx, c) {
  const base = `/projects/${ctx.projectId}/classes/${enc(c.name)}`;
  const save = (fn) => classCall(ctx, fn);
  const color = h("input", {
    type: "color",
    class: "cls-color",
    value: c.hex,
    title: "Color",
    "aria-label": `Color of ${c.name}`,
    onchange: (e) => save(() => patch(base, { color: e.target.value })),
  });
  const name = h("input", {
    class: "cls-name",
    value: c.name,
    "aria-label": "Class name",
    maxlength: 64,
    onchange: (e) => {
      const v = e.target.value.trim();
      if (v && v !== c.name) save(() => patch(base, { name: v }));
      else e.target.value = c.name;
    },
  });
  const exportId = h("input", {
    class: "cls-export",
    type: "number",
    min: 1,
    max: 65535,
    value: String(c.export_id),
    title: "Export id written to .label files",
    "aria-label": `Export id of ${c.name}`,
    onchange: (e) => save(() => patch(base, { export_id: Number(e.target.value) })),
  });
  const remove = h(
    "button",
    {
      class: "icon cls-delete",
      title: `Remove class ${c.name}`,
      "aria-label": `Remove class ${c.name}`,
      onclick: () => {
        if (window.confirm(`Remove class “${c.name}”?`)) save(() => del(base));
      },
    },
    "×",
  );
  const chips = c.prompts.map((p, i) =>
    h(
      "span",
      { class: "prompt", dataset: { index: String(i) } },
      h("span", { class: "prompt-text" }, p),
      h(
        "button",
        {
          class: "prompt-remove",
          title: `Remove prompt ${p}`,
          "aria-label": `Remove prompt ${p}`,
          onclick: () => save(() => del(`${base}/prompts/${i}`)),
        },
        "×",
      ),
    ),
  );
  const add = h("input", {
    class: "prompt-add",
    placeholder: "+ prompt",
    "aria-label": `Add a prompt to ${c.name}`,
    maxlength: 200,
    onkeydown: (e) => {
      if (e.key !== "Enter") return;
      e.preventDefault();
      const v = e.target.value.trim();
      if (v) save(() => post(`${base}/prompts`, { prompt: v }));
    },
  });
  return h(
    "li",
    { class: "class-row", dataset: { class: c.name } },
    h("div", { class: "class-line" }, color, name, exportId, remove),
    h("div", { class: "prompts" }, chips, add),
  );
}

function addClassForm(ctx) {
  const classes = ctx.state.classes;
  const name = h("input", { placeholder: "new class", maxlength: 64, id: "new-class-name", "aria-label": "New class name" });
  const color = h("input", { type: "color", value: "#888888", "aria-label": "New class color" });
  const nextId = Math.max(0, ...classes.map((c) => c.export_id)) + 1;
  const exportId = h("input", { type: "number", min: 1, max: 65535, value: String(Math.min(nextId, 65535)), class: "cls-export", "aria-label": "New class export id" });
  const prompts = h("input", { placeholder: "prompts, comma separated", id: "new-class-prompts", "aria-label": "New class prompts" });
  return h(
    "form",
    {
      class: "add-class",
      onsubmit: async (e) => {
        e.preventDefault();
        const list = prompts.value.split(",").map((p) => p.trim()).filter(Boolean);
        const n = name.value.trim();
        if (!n) return;
        await classCall(ctx, () =>
          post(`/projects/${ctx.projectId}/classes`, { name: n, color: color.value, export_id: Number(exportId.value), prompts: list.length ? list : [n] }),
        );
      },
    },
    h("div", { class: "class-line" }, color, name, exportId, h("button", { class: "btn small", type: "submit" }, "Add")),
    prompts,
  );
}

export function renderClasses(ctx) {
  const classes = ctx.state.classes;
  replace(
    ctx.els.classes,
    h("div", { class: "card-head" }, h("h2", {}, "Classes & prompts"), h("span", { class: "muted small" }, `${classes.length} classes`)),
    h("p", { class: "muted small" }, "Color · name · export id. Enter adds a prompt; the next run uses the edits."),
    h("p", { class: "editor-status", role: "status" }),
    h("ol", { class: "class-list" }, classes.map((c) => classRow(ctx, c))),
    addClassForm(ctx),
  );
}
