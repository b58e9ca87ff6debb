// Pipeline parameters: a form built from the server's field list (GET /pipeline → form), saved as the
// project's flat form values. The server checks every value and names the failing field in its answer.

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

export function renderParams(ctx) {
  const { state, projectId, toast } = ctx;
  const fields = ctx.pipeline.form;
  const form = state.project.form;
  const inputs = {};
  const error = h("p", { class: "error", role: "alert" });
  const labels = fields.map((field) => {
    const el = input(field, form[field.name]);
    inputs[field.name] = el;
    return h(
      "label",
      { class: `param ${field.kind}`, title: field.help || null, dataset: { param: field.name } },
      h("span", {}, field.label),
      el,
    );
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
          const values = {};
          for (const field of fields) values[field.name] = valueOf(field, inputs[field.name]);
          try {
            state.project = await patch(`/projects/${projectId}`, { form: values });
            toast("Parameters saved");
            renderParams(ctx);
          } catch (err) {
            error.textContent = err.message;
            const f = err instanceof ApiError ? err.field() : null;
            if (f && inputs[f]) inputs[f].classList.add("invalid");
          }
        },
      },
      labels,
      error,
      h("div", { class: "row end" }, save),
    ),
  );
}
