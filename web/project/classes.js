// Classes & prompts editor: colour, name and export id per class, prompt chips (Enter adds one), the raw
// ground-truth ids each class is evaluated against, and a form for a new class. A new class gets the
// server's most distinct unused colour (never the viewer's unlabeled grey); its ground-truth ids are picked
// from the raw ids present in the dataset's labels (GET /projects/{id}/gt-ids, with names where known), and
// named objects no class maps yet (the demo's traffic cones, benches, bollards …) are offered as one-click
// suggestions. Each class also says whether it is a thing (a countable object the tracks stage follows and
// gives instance ids) and, for a thing, the raw id its points export while it moves (SemanticKITTI's
// 252-259; empty: none). Every edit is saved at once; the next run uses it.

import { ApiError, del, enc, get, patch, post, url } from "../api.js";
import { h, replace } from "../dom.js";

const NOT_EVALUATED = "none: not evaluated";
/** Raw ids never offered as a class of their own: SemanticKITTI's "unlabeled" and "outlier". */
const NEVER_SUGGESTED = new Set([0, 1]);

/**
 * Run one class-list request; on success show the new list, on failure its message (in the editor's
 * status line, or through `onError` for an editor that shows it beside its own field).
 */
async function classCall(ctx, fn, onError = null) {
  const status = ctx.els.classes.querySelector(".editor-status");
  try {
    const res = await fn();
    ctx.state.classes = res.data;
    ctx.state.nextColor = res.next_color;
    renderClasses(ctx);
    const saved = ctx.els.classes.querySelector(".editor-status");
    saved.textContent = "Saved";
    saved.className = "editor-status ok";
    if (ctx.render.next) ctx.render.next();
    return true;
  } catch (err) {
    if (onError) {
      if (status) status.textContent = ""; // a "Saved" of an earlier edit no longer holds
      onError(err);
    } else if (status) {
      status.textContent = err.message;
      status.className = "editor-status error";
    }
    return false;
  }
}

function idName(ctx, id) {
  const ids = ctx.state.gtIds;
  return ids && ids.names[String(id)] ? ids.names[String(id)] : null;
}

/** Classes whose ground-truth ids include raw id `id` (from the current class list, not the cached scan). */
function usersOf(ctx, id) {
  return ctx.state.classes.filter((c) => c.gt_ids.includes(id)).map((c) => c.name);
}

function idText(ctx, id) {
  const name = idName(ctx, id);
  return name ? `${id} ${name}` : `${id}`;
}

/** A multi-select over the dataset's raw ids (plus any already chosen that the dataset lacks). */
function gtSelect(ctx, chosen, attrs) {
  const ids = ctx.state.gtIds;
  const present = ids ? ids.data : [];
  const all = new Map(present.map((r) => [r.id, r]));
  for (const id of chosen) if (!all.has(id)) all.set(id, { id, name: idName(ctx, id), points: 0 });
  const options = [...all.values()]
    .sort((a, b) => a.id - b.id)
    .map((r) => {
      const users = usersOf(ctx, r.id);
      const used = users.length ? ` · ${users.join(", ")}` : "";
      const count = r.points ? ` · ${r.points.toLocaleString()} pts` : " · not in the dataset";
      return h("option", { value: String(r.id), selected: chosen.includes(r.id) }, `${r.id} ${r.name || "(no name)"}${count}${used}`);
    });
  return h("select", { multiple: true, size: Math.min(8, Math.max(3, options.length)), ...attrs }, options);
}

function selectedIds(select) {
  return [...select.selectedOptions].map((o) => Number(o.value));
}

function gtSummary(ctx, ids) {
  return ids.length ? ids.map((id) => idText(ctx, id)).join(", ") : NOT_EVALUATED;
}

function gtEditor(ctx, c, save) {
  const base = `/projects/${ctx.projectId}/classes/${enc(c.name)}`;
  const open = ctx.state.gtOpen === c.name;
  const summary = h("span", { class: `gt-summary${c.gt_ids.length ? "" : " muted"}` }, gtSummary(ctx, c.gt_ids));
  const toggle = h(
    "button",
    {
      type: "button",
      class: "btn ghost small gt-edit",
      "aria-label": `Edit ground-truth ids of ${c.name}`,
      onclick: () => {
        ctx.state.gtOpen = open ? null : c.name;
        renderClasses(ctx, { keepTyped: true });
      },
    },
    open ? "Close" : "Edit",
  );
  const parts = [h("div", { class: "gt-line small" }, h("span", { class: "muted" }, "Ground truth: "), summary, toggle)];
  if (open) {
    const select = gtSelect(ctx, c.gt_ids, { class: "gt-select", "aria-label": `Ground-truth ids of ${c.name}` });
    parts.push(
      h(
        "div",
        { class: "gt-pick" },
        select,
        h("p", { class: "muted small" }, ctx.state.gtIds && !ctx.state.gtIds.has_ground_truth ? "The dataset has no ground-truth labels." : `Ctrl/⌘-click picks several; none selected = ${NOT_EVALUATED}.`),
        h(
          "div",
          { class: "row" },
          h("button", { type: "button", class: "btn small primary gt-save", onclick: () => { ctx.state.gtOpen = null; save(() => patch(base, { gt_ids: selectedIds(select) })); } }, "Save ids"),
          h("button", { type: "button", class: "btn small ghost gt-clear", onclick: () => { ctx.state.gtOpen = null; save(() => patch(base, { gt_ids: [] })); } }, "Not evaluated"),
        ),
      ),
    );
  }
  return parts;
}

/**
 * The class's object fields: a "thing" checkbox and its moving raw id (empty = none). A failed save leaves
 * the value typed and shows the server's message beside the fields, the input it names marked, as the
 * parameter form does.
 */
function objectFields(ctx, c) {
  const base = `/projects/${ctx.projectId}/classes/${enc(c.name)}`;
  const error = h("p", { class: "error small cls-object-error", role: "alert" });
  const inputs = {};
  const save = async (body, input) => {
    error.textContent = "";
    for (const el of Object.values(inputs)) el.classList.remove("invalid");
    await classCall(ctx, () => patch(base, body), (err) => {
      error.textContent = err.message;
      const f = err instanceof ApiError ? err.field() : null;
      (inputs[f] || input).classList.add("invalid");
    });
  };
  inputs.thing = h("input", {
    type: "checkbox",
    class: "cls-thing",
    checked: Boolean(c.thing),
    "aria-label": `${c.name} is a thing`,
    // A stuff class has no moving id: unticking a thing clears it in the same save (the field shows it).
    onchange: (e) => save(e.target.checked ? { thing: true } : { thing: false, moving_id: null }, e.target),
  });
  inputs.moving_id = h("input", {
    type: "number",
    class: "cls-moving",
    min: 1,
    max: 65535,
    value: c.moving_id === null || c.moving_id === undefined ? "" : String(c.moving_id),
    placeholder: "none",
    disabled: !c.thing,
    title: c.thing ? "Raw id its points export while the object moves (empty: none)" : "Only a thing has a moving id",
    "aria-label": `Moving id of ${c.name}`,
    onchange: (e) => {
      const v = e.target.value.trim();
      save({ moving_id: v === "" ? null : Number(v) }, e.target);
    },
  });
  return h(
    "div",
    { class: "object-line small" },
    h("label", { class: "inline", title: "A countable object: tracked through the sequence, with instance ids" }, inputs.thing, " thing"),
    h("label", { class: "inline" }, "moving id ", inputs.moving_id),
    error,
  );
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
    objectFields(ctx, c),
    h("div", { class: "prompts" }, chips, add),
    gtEditor(ctx, c, save),
  );
}

/** Named raw ids present in the dataset that no class maps (e.g. the demo's traffic cones). */
function suggestions(ctx) {
  const ids = ctx.state.gtIds;
  if (!ids) return [];
  const names = new Set(ctx.state.classes.map((c) => c.name));
  return ids.data.filter((r) => r.name && !usersOf(ctx, r.id).length && !NEVER_SUGGESTED.has(r.id) && !names.has(r.name));
}

/**
 * The new class's object fields: "thing" starts undecided (the server then follows SemanticKITTI's things
 * by name and export id, else stuff) until ticked or unticked; the moving id is sent when typed. A refused
 * add shows the server's message beside them, the input its 422 names marked.
 */
function newObjectFields() {
  const thing = h("input", { type: "checkbox", id: "new-class-thing", "aria-label": "New class is a thing" });
  thing.indeterminate = true;
  const moving = h("input", {
    type: "number",
    min: 1,
    max: 65535,
    placeholder: "none",
    class: "cls-moving",
    id: "new-class-moving",
    title: "Raw id its points export while the object moves (empty: none; only a thing moves)",
    "aria-label": "New class moving id",
  });
  thing.addEventListener("change", () => (moving.disabled = !thing.checked));
  const error = h("p", { class: "error small", id: "new-class-object-error", role: "alert" });
  const inputs = { thing, moving_id: moving };
  return {
    line: h(
      "div",
      { class: "object-line small" },
      h("label", { class: "inline", title: "A countable object: tracked through the sequence, with instance ids (undecided: SemanticKITTI's things by name)" }, thing, " thing"),
      h("label", { class: "inline" }, "moving id ", moving),
      error,
    ),
    body() {
      const out = {};
      if (!thing.indeterminate) out.thing = thing.checked;
      const v = moving.value.trim();
      if (v !== "" && !moving.disabled) out.moving_id = Number(v);
      return out;
    },
    clear() {
      error.textContent = "";
      for (const el of Object.values(inputs)) el.classList.remove("invalid");
    },
    /** Shows a refused add beside the fields when it is about them; returns whether it was. */
    show(err) {
      const f = err instanceof ApiError ? err.field() : null;
      // A field's own check names it in the 422's loc; the class list's rules (a moving id on a stuff
      // class, one equal to the export id) name the class entry and say the field in the message.
      const input = inputs[f] || (/\bmoving_id\b/.test(err.message) ? moving : /\bthing (must|is)\b/.test(err.message) ? thing : null);
      if (!input) return false;
      error.textContent = err.message;
      input.classList.add("invalid");
      return true;
    },
  };
}

function addClassForm(ctx) {
  const classes = ctx.state.classes;
  const name = h("input", { placeholder: "new class", maxlength: 64, id: "new-class-name", "aria-label": "New class name" });
  let colorTouched = false;
  const color = h("input", {
    type: "color",
    value: ctx.state.nextColor || "#e6194b",
    id: "new-class-color",
    title: "The most distinct unused colour; change it if you like",
    "aria-label": "New class color",
    oninput: () => (colorTouched = true),
  });
  const usedExport = new Set(classes.map((c) => c.export_id));
  const nextId = Math.max(0, ...classes.map((c) => c.export_id)) + 1;
  const exportId = h("input", { type: "number", min: 1, max: 65535, value: String(Math.min(nextId, 65535)), class: "cls-export", id: "new-class-export", "aria-label": "New class export id" });
  const prompts = h("input", { placeholder: "prompts, comma separated", id: "new-class-prompts", "aria-label": "New class prompts" });
  const object = newObjectFields();
  const gt = gtSelect(ctx, [], { id: "new-class-gt", "aria-label": "New class ground-truth ids" });
  const gtNote = h("span", { class: "muted small", id: "new-class-gt-summary" }, `Ground truth: ${NOT_EVALUATED}`);
  gt.addEventListener("change", () => (gtNote.textContent = `Ground truth: ${gtSummary(ctx, selectedIds(gt))}`));
  const offer = suggestions(ctx).map((r) =>
    h(
      "button",
      {
        type: "button",
        class: "btn small ghost suggestion",
        dataset: { rawId: String(r.id) },
        title: `${r.points.toLocaleString()} points in the dataset carry raw id ${r.id}; no class maps it yet`,
        onclick: () => {
          name.value = r.name;
          prompts.value = r.name.replace(/-/g, " ");
          if (!usedExport.has(r.id) && r.id >= 1) exportId.value = String(r.id);
          for (const o of gt.options) o.selected = Number(o.value) === r.id;
          gt.dispatchEvent(new Event("change"));
        },
      },
      `+ ${r.name} (${r.id})`,
    ),
  );
  return h(
    "form",
    {
      class: "add-class",
      onsubmit: async (e) => {
        e.preventDefault();
        const list = prompts.value.split(",").map((p) => p.trim()).filter(Boolean);
        const n = name.value.trim();
        if (!n) return;
        const body = { name: n, export_id: Number(exportId.value), prompts: list.length ? list : [n], gt_ids: selectedIds(gt) };
        if (colorTouched) body.color = color.value; // else the server picks the same distinct colour
        Object.assign(body, object.body());
        object.clear();
        await classCall(ctx, () => post(`/projects/${ctx.projectId}/classes`, body), (err) => {
          if (object.show(err)) return;
          const status = ctx.els.classes.querySelector(".editor-status");
          status.textContent = err.message;
          status.className = "editor-status error";
        });
      },
    },
    offer.length ? h("div", { class: "suggestions" }, h("span", { class: "muted small" }, "In the ground truth, not yet a class: "), offer) : null,
    h("div", { class: "class-line" }, color, name, exportId, h("button", { class: "btn small", type: "submit" }, "Add")),
    object.line,
    prompts,
    gtNote,
    gt,
  );
}

async function loadGtIds(ctx) {
  if (ctx.state.gtIds || ctx.state.gtIdsLoading) return;
  ctx.state.gtIdsLoading = true;
  try {
    ctx.state.gtIds = await get(`/projects/${ctx.projectId}/gt-ids`);
  } catch (err) {
    ctx.state.gtIds = { data: [], names: {}, has_ground_truth: false, error: err.message };
  }
  ctx.state.gtIdsLoading = false;
  renderClasses(ctx, { keepTyped: true });
}

/** Prompts typed but not yet added (Enter), by class name, and the class whose prompt field has focus. */
function typedPrompts(ctx) {
  const typed = new Map();
  let focused = null;
  for (const input of ctx.els.classes.querySelectorAll(".prompt-add")) {
    const name = input.closest(".class-row").dataset.class;
    if (input.value) typed.set(name, input.value);
    if (document.activeElement === input) focused = name;
  }
  return { typed, focused };
}

/**
 * Draw the class list. `keepTyped`: a redraw nobody asked for (the ground-truth ids arriving) keeps what
 * the user is typing into a prompt field, and its focus; a redraw after a saved edit starts clean.
 */
export function renderClasses(ctx, { keepTyped = false } = {}) {
  const classes = ctx.state.classes;
  const kept = keepTyped ? typedPrompts(ctx) : null;
  replace(
    ctx.els.classes,
    h("div", { class: "card-head" }, h("h2", {}, "Classes & prompts"), h("span", { class: "muted small" }, `${classes.length} classes`)),
    h(
      "p",
      { class: "muted small" },
      "Color · name · export id; thing (a tracked object) and its moving id. Enter adds a prompt; the next run uses the edits. ",
      // The file the create form's "upload a class list" takes: a new project starts with these classes.
      h("a", { href: url(`/projects/${ctx.projectId}/classes.yaml`), download: "", id: "download-classes" }, "Download the class list (.yaml)"),
    ),
    h("p", { class: "editor-status", role: "status" }),
    h("ol", { class: "class-list" }, classes.map((c) => classRow(ctx, c))),
    addClassForm(ctx),
  );
  if (kept) {
    for (const input of ctx.els.classes.querySelectorAll(".prompt-add")) {
      const name = input.closest(".class-row").dataset.class;
      if (kept.typed.has(name)) input.value = kept.typed.get(name);
      if (kept.focused === name) input.focus();
    }
  }
  loadGtIds(ctx);
}
