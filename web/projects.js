// Project list and the create-project form.

import { get, post, postFile } from "./api.js";
import { checkSummary } from "./dataset-check.js";
import { fmtPct, fmtTime, h, replace, statusChip } from "./dom.js";
import { pipelineInfo } from "./pipeline.js";
import { posesOption } from "./poses-option.js";

/** The class preset a new project gets unless the user picks another (ProjectCreate.schema_name's default). */
const DEFAULT_PRESET = "semantickitti";

function projectCard(p) {
  const last = p.last_run;
  return h(
    "a",
    { class: "card project-card", href: `#/projects/${p.id}`, dataset: { projectId: String(p.id) } },
    h("div", { class: "project-card-head" }, h("h3", {}, p.name), p.is_demo ? h("span", { class: "chip demo" }, "demo") : null),
    h("p", { class: "muted path" }, p.dataset.kind === "demo" ? "Built-in demo sequence" : p.sequences && p.sequences.length > 1 ? `${p.sequences.length} sequences: ${p.sequences.map((s) => s.name).join(", ")}` : p.dataset.path),
    h(
      "dl",
      { class: "facts" },
      h("div", {}, h("dt", {}, "frames"), h("dd", {}, p.sequences && p.sequences.length > 1 ? p.sequences.reduce((n, s) => n + (s.dataset.frames || 0), 0) : p.dataset.frames ?? "–")),
      h("div", {}, h("dt", {}, "classes"), h("dd", {}, p.num_classes)),
      h("div", {}, h("dt", {}, "labeler"), h("dd", {}, p.form.labeler)),
      h("div", {}, h("dt", {}, "runs"), h("dd", {}, p.runs_count)),
    ),
    h(
      "div",
      { class: "project-card-foot" },
      last ? statusChip(last.status) : h("span", { class: "muted" }, "no runs yet"),
      last ? h("span", { class: "muted" }, `run ${last.number} · ${fmtTime(last.finished_at || last.created_at)}`) : null,
      last && last.miou !== null && last.miou !== undefined
        ? h("span", { class: "card-miou", title: `camera-view mIoU of the ${last.miou_row} labels` }, h("strong", {}, fmtPct(last.miou)), " mIoU")
        : null,
    ),
  );
}

/** The "several sequences" list: one folder per line, "name = folder" to name one. */
export function sequenceLines(text) {
  return text
    .split("\n")
    .map((line) => line.trim())
    .filter((line) => line)
    .map((line) => {
      const m = line.match(/^([A-Za-z0-9][A-Za-z0-9_.-]*)\s*=\s*(.+)$/);
      return m ? { name: m[1], path: m[2].trim() } : { path: line };
    });
}

/** Largest class-list file the server reads (leap_core.schema.MAX_CLASS_LIST_BYTES): a bigger one is
 * refused here before its bytes travel. */
const MAX_CLASS_FILE_BYTES = 256 * 1024;
const UPLOAD = "__upload__";
/** Pause in typing after which a typed dataset path is checked. */
const TYPED_PATH_DELAY_MS = 400;

/** The class picker: every built-in preset by name, with its class count and (as a hint) its classes, or
 * an uploaded class-list file (the `classes:` part of a preset), read and checked by the server on pick.
 * `classList()` is what the create request sends: null for a preset, the checked list for a file
 * (undefined while a file is missing or refused). */
function presetPicker(presets) {
  const select = h(
    "select",
    { id: "new-preset", name: "schema_name" },
    presets.map((p) =>
      h("option", { value: p.name, selected: p.name === DEFAULT_PRESET }, `${p.name} (${p.classes.length} classes)`),
    ),
    h("option", { value: UPLOAD }, "Upload a class list (.yaml)…"),
  );
  const file = h("input", { type: "file", id: "new-class-file", accept: ".yaml,.yml,application/yaml,text/yaml", hidden: true });
  const hint = h("p", { class: "muted small", id: "new-preset-classes" });
  let uploaded;
  const showClasses = () => {
    file.hidden = select.value !== UPLOAD;
    hint.classList.remove("error");
    if (select.value === UPLOAD) {
      hint.textContent = uploaded ? `${uploaded.name}: ${uploaded.classes.map((c) => c.name).join(", ")}` : "Pick a class-list file: the classes part of a preset, or a project's downloaded class list.";
      return;
    }
    const p = presets.find((x) => x.name === select.value);
    hint.textContent = p ? p.classes.join(", ") : "";
  };
  const refuse = (message) => {
    uploaded = undefined;
    hint.textContent = message;
    hint.classList.add("error");
  };
  select.addEventListener("change", showClasses);
  file.addEventListener("change", async () => {
    uploaded = undefined;
    const f = file.files[0];
    if (!f) return showClasses();
    if (f.size > MAX_CLASS_FILE_BYTES) return refuse(`${f.name}: the file is larger than ${MAX_CLASS_FILE_BYTES / 1024} KiB`);
    hint.textContent = `Checking ${f.name}…`;
    try {
      const list = await postFile("/class-lists", f, "application/yaml");
      if (file.files[0] !== f) return; // another file was picked meanwhile
      uploaded = { name: list.name, description: list.description, classes: list.classes };
      showClasses();
    } catch (err) {
      if (file.files[0] === f) refuse(`${f.name}: ${err.message}`);
    }
  });
  showClasses();
  const classList = () => (select.value !== UPLOAD ? null : uploaded);
  return { select, file, hint, classList };
}

function createForm(datasets, presets, { toast, onCreated }) {
  const name = h("input", { id: "new-name", name: "name", required: true, maxlength: 120, placeholder: "My sequence" });
  const kindDemo = h("input", { type: "radio", name: "kind", value: "demo", id: "kind-demo" });
  const kindFolder = h("input", { type: "radio", name: "kind", value: "folder", id: "kind-folder", checked: true });
  const kindSeveral = h("input", { type: "radio", name: "kind", value: "several", id: "kind-several" });
  // Several sequences (e.g. SemanticKITTI 00-10) labeled with one class schema: one folder per line,
  // optionally "name = folder" (the name defaults to the folder's, e.g. 00).
  const paths = h("textarea", { id: "new-paths", rows: 4, spellcheck: "false", placeholder: "one sequence folder per line (name = folder to name it)" });
  paths.addEventListener("input", () => (kindSeveral.checked = true));
  const select = h(
    "select",
    { id: "new-dataset" },
    h("option", { value: "" }, datasets.data.length ? "— pick a dataset folder —" : "— no KITTI sequences found in the data roots —"),
    datasets.data.map((d) =>
      h("option", { value: d.path }, `${d.path}  (${d.frames} frames${d.has_ground_truth ? ", ground truth" : ""})`),
    ),
  );
  const path = h("input", { id: "new-path", placeholder: "or type a path inside a data root", spellcheck: "false" });
  const checkBox = h("div", { class: "check-slot" });
  // A typed folder is checked by the server (GET /datasets/check, confined to the data roots as at
  // creation) once typing pauses, so the form shows what a listed folder shows before "Create project".
  let typedTimer = null;
  let asked = "";
  const showCheck = () => {
    clearTimeout(typedTimer);
    const typed = path.value.trim();
    asked = typed;
    const d = datasets.data.find((x) => x.path === typed);
    if (d || !typed) {
      replace(checkBox, d ? checkSummary(d.check) : null);
      return;
    }
    replace(checkBox);
    typedTimer = setTimeout(async () => {
      replace(checkBox, h("p", { class: "muted small", id: "new-dataset-checking" }, "Checking the folder…"));
      try {
        const found = await get(`/datasets/check?path=${encodeURIComponent(typed)}`);
        if (asked === typed) replace(checkBox, checkSummary(found.check));
      } catch (err) {
        if (asked === typed) replace(checkBox, h("p", { class: "error small", id: "new-dataset-refused" }, err.message));
      }
    }, TYPED_PATH_DELAY_MS);
  };
  select.addEventListener("change", () => {
    if (kindSeveral.checked) {
      // The picker adds folders to the list while "several" is chosen.
      if (select.value && !sequenceLines(paths.value).some((l) => l.path === select.value)) {
        paths.value = `${paths.value.replace(/\s+$/, "")}${paths.value.trim() ? "\n" : ""}${select.value}`;
      }
      select.value = "";
      return;
    }
    if (select.value) path.value = select.value;
    kindFolder.checked = true;
    showCheck();
  });
  path.addEventListener("input", () => {
    kindFolder.checked = true;
    showCheck();
  });
  const preset = presetPicker(presets);
  const poses = posesOption();
  const error = h("p", { class: "error", role: "alert" });
  const submit = h("button", { class: "btn primary", type: "submit", id: "create-project" }, "Create project");
  const form = h(
    "form",
    {
      class: "card create",
      id: "create-form",
      onsubmit: async (e) => {
        e.preventDefault();
        error.textContent = "";
        const classList = preset.classList();
        if (classList === undefined) {
          error.textContent = "Pick a valid class-list file, or one of the presets.";
          return;
        }
        const body = { name: name.value.trim(), estimate_poses: poses.checked() };
        if (classList) body.class_list = classList;
        else body.schema_name = preset.select.value;
        if (kindSeveral.checked) body.sequences = sequenceLines(paths.value);
        else body.dataset = kindDemo.checked ? { kind: "demo" } : { kind: "folder", path: path.value.trim() };
        submit.disabled = true;
        try {
          const p = await post("/projects", body);
          const partial = p.dataset.check && p.dataset.check.verdict === "partial";
          toast(`Project “${p.name}” created${partial ? `: ${p.dataset.check.summary}, see the dataset check` : ""}`);
          onCreated(p);
        } catch (err) {
          error.textContent = err.message;
        } finally {
          submit.disabled = false;
        }
      },
    },
    h("h2", {}, "New project"),
    h("label", { class: "field" }, h("span", {}, "Name"), name),
    h(
      "fieldset",
      { class: "field" },
      h("legend", {}, "Dataset"),
      h("label", { class: "radio" }, kindFolder, h("span", {}, "KITTI-layout sequence folder")),
      h("div", { class: "indent stack" }, select, path, checkBox),
      h("label", { class: "radio" }, kindSeveral, h("span", {}, "Several sequence folders, one class schema (pick them above or type them)")),
      h("div", { class: "indent stack" }, paths),
      h("label", { class: "radio" }, kindDemo, h("span", {}, "Built-in demo street (generated on first run)")),
    ),
    h("label", { class: "field" }, h("span", {}, "Classes"), preset.select),
    preset.file,
    preset.hint,
    poses.element,
    h(
      "p",
      { class: "muted small" },
      `Data roots: ${datasets.roots.join(", ")} (the server's setting: leap serve --data-root DIR, or LEAP_DATA_ROOTS). `,
      "The classes can be edited after creation.",
    ),
    error,
    h("div", { class: "row end" }, submit),
  );
  return form;
}

export async function renderProjects(root, { toast }) {
  const [projects, datasets, pipeline] = await Promise.all([get("/projects"), get("/datasets"), pipelineInfo()]);
  const list = h(
    "div",
    { class: "project-grid", id: "project-list" },
    projects.data.length ? projects.data.map(projectCard) : h("p", { class: "muted" }, "No projects yet: create one."),
  );
  replace(
    root,
    h("div", { class: "page-head" }, h("h1", {}, "Projects"), h("span", { class: "muted" }, `${projects.count} project${projects.count === 1 ? "" : "s"}`)),
    h(
      "div",
      { class: "layout" },
      h("section", { class: "main-col" }, list),
      h("aside", { class: "side-col" }, createForm(datasets, pipeline.presets, { toast, onCreated: (p) => (window.location.hash = `#/projects/${p.id}`) })),
    ),
  );
  return () => {};
}

