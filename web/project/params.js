// Pipeline parameters: a form built from the server's field list (GET /pipeline → form), saved as the
// project's flat form values. The server checks every value and names the failing field in its answer.
// A field the current choices ignore (another labeler's setting, a setting of a switched-off stage) is
// disabled and says why; which labeler or stage a field belongs to comes from the server's field records.

import { ApiError, patch } from "../api.js";
import { h, replace } from "../dom.js";

function input(field, value) {
  const name = field.name;
  if (field.kind === "select") {
    return h("select", { name }, field.choices.map((c) => h("option", { value: c.value, selected: value === c.value }, c.label)));
  }
  if (field.kind === "checkbox") return h("input", { type: "checkbox", name, checked: Boolean(value) });
  // "number" and "integer": the server refuses a fraction for an integer field.
  return h("input", { type: "number", name, step: field.step, min: field.minimum, max: field.maximum, value: String(value) });
}

function valueOf(field, el) {
  if (field.kind === "checkbox") return el.checked;
  if (field.kind === "select") return el.value;
  return Number(el.value);
}

/** Why the form's current values make `field` ineffective, or null (the rule of leap_core.pipeline.steering). */
export function ignoredReason(ctx, field, values) {
  const labelers = new Map(ctx.pipeline.labelers.map((l) => [l.name, l.label]));
  if (field.labeler && values.labeler !== undefined && values.labeler !== field.labeler) {
    return `only the ${labelers.get(field.labeler) || field.labeler} labeler uses it; the ${labelers.get(values.labeler) || values.labeler} labeler ignores it`;
  }
  if (field.stage) {
    const stage = ctx.stages.get(field.stage);
    if (stage && stage.switch && values[stage.switch] === false) {
      const sw = ctx.pipeline.form.find((f) => f.name === stage.switch);
      return `the ${stage.label} stage is off (${sw ? sw.label : stage.switch} is unticked)`;
    }
  }
  return null;
}

export function renderParams(ctx) {
  const { state, projectId, toast } = ctx;
  const fields = ctx.pipeline.form;
  const form = state.project.form;
  const inputs = {};
  const notes = {};
  const labels = {};
  const error = h("p", { class: "error", role: "alert" });

  const current = () => {
    const values = {};
    for (const field of fields) values[field.name] = valueOf(field, inputs[field.name]);
    return values;
  };
  // Grey out what the current (possibly unsaved) choices ignore, and say why.
  const refresh = () => {
    const values = current();
    for (const field of fields) {
      const why = ignoredReason(ctx, field, values);
      inputs[field.name].disabled = Boolean(why);
      labels[field.name].classList.toggle("ignored", Boolean(why));
      labels[field.name].title = why ? `Ignored: ${why}` : field.help || "";
      notes[field.name].textContent = why ? `Ignored: ${why}` : "";
      notes[field.name].hidden = !why;
    }
  };

  const rows = fields.map((field) => {
    const el = input(field, form[field.name]);
    el.addEventListener("change", refresh);
    inputs[field.name] = el;
    notes[field.name] = h("small", { class: "param-note", hidden: true }); // not a span: "> span" is the label
    labels[field.name] = h(
      "label",
      { class: `param ${field.kind}`, title: field.help || null, dataset: { param: field.name } },
      h("span", {}, field.label),
      el,
      notes[field.name],
    );
    return labels[field.name];
  });
  const save = h("button", { class: "btn small primary", type: "submit", id: "save-params" }, "Save parameters");
  replace(
    ctx.els.params,
    h("h2", {}, "Parameters"),
    h(
      "form",
      {
        class: "params-grid",
        novalidate: true, // the server checks every value and names the field in its answer
        onsubmit: async (e) => {
          e.preventDefault();
          error.textContent = "";
          for (const el of Object.values(inputs)) el.classList.remove("invalid");
          const values = current();
          try {
            state.project = await patch(`/projects/${projectId}`, { form: values });
            toast("Parameters saved");
            renderParams(ctx);
            if (ctx.render.next) ctx.render.next();
            if (ctx.render.check) ctx.render.check(); // a new labeler changes what the dataset allows
          } catch (err) {
            error.textContent = err.message;
            const f = err instanceof ApiError ? err.field() : null;
            if (f && inputs[f]) inputs[f].classList.add("invalid");
          }
        },
      },
      rows,
      error,
      h("div", { class: "row end" }, save),
    ),
  );
  refresh();
}
