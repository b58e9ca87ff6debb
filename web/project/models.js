// LiDAR-only models of the project: "Train a model" on the latest finished run's final labels (corrections
// win; a background job with live progress, cancel and resume), the trained models with their cards
// (classes, data and runs seen, validation IoU per class, when, settings), and "Label with a model" on one
// of the project's sequences (or a sequence folder in a data root), whose labels download as a zip. Mounted by project.js after the other cards;
// polls the jobs while one is queued or working.

import { get, post, url } from "../api.js";
import { fmtPct, fmtTime, h, replace, statusChip } from "../dom.js";

const ACTIVE = new Set(["queued", "running"]);
const RESUMABLE = new Set(["cancelled", "failed", "interrupted"]);
const POLL_MS = 700;

function numberField(id, label, value, min, max) {
  return h(
    "label",
    { class: "field" },
    h("span", { class: "muted small" }, label),
    h("input", { id, type: "number", min, max, step: 1, value: String(value) }),
  );
}

function trainForm(ctx, card) {
  const names = ctx.state.project.sequences.map((s) => s.name);
  const seqPick = h(
    "select",
    { id: "model-val-sequence", "aria-label": "Sequence held apart", hidden: true },
    names.map((n) => h("option", { value: n }, n)),
  );
  const by = h(
    "select",
    {
      id: "model-validation",
      "aria-label": "Validation",
      onchange: (e) => (seqPick.hidden = e.target.value !== "sequence"),
    },
    h("option", { value: "block" }, "blocks of frames"),
    names.length > 1 ? h("option", { value: "sequence" }, "one whole sequence") : null,
  );
  const train = async () => {
    const val = (id) => Number(card.querySelector(`#${id}`).value);
    const body = {
      name: card.querySelector("#model-name").value.trim() || "model",
      steps: val("model-steps"),
      points_per_scan: val("model-points"),
      val_block: val("model-val-block"),
      val_every: val("model-val-every"),
      validation: by.value,
    };
    if (by.value === "sequence") body.validation_sequence = seqPick.value;
    try {
      await post(`/projects/${ctx.projectId}/models`, body);
      await refresh(ctx, card);
    } catch (err) {
      ctx.toast(err.message, "error");
    }
  };
  return h(
    "div",
    { class: "model-train" },
    h(
      "label",
      { class: "field" },
      h("span", { class: "muted small" }, "Name"),
      h("input", { id: "model-name", maxlength: 80, value: "model" }),
    ),
    numberField("model-steps", "Steps", 200, 1, 100000),
    numberField("model-points", "Points per scan", 8192, 256, 1000000),
    numberField("model-val-block", "Frames per validation block", 10, 1, 100000),
    numberField("model-val-every", "Every n-th block validates", 5, 2, 1000),
    h("label", { class: "field" }, h("span", { class: "muted small" }, "Validation"), by, seqPick),
    h("button", { class: "btn", id: "train-model", onclick: train }, "Train a model"),
  );
}

function jobItem(ctx, card, job) {
  const act = async (action) => {
    try {
      await post(`/projects/${ctx.projectId}/model-jobs/${job.id}/${action}`, {});
      await refresh(ctx, card);
    } catch (err) {
      ctx.toast(err.message, "error");
    }
  };
  const what = job.kind === "train" ? `Training “${job.name}”` : `Labeling ${job.name} with model ${job.model_id}`;
  return h(
    "li",
    { class: "model-job", dataset: { jobId: String(job.id), kind: job.kind, status: job.status } },
    h("span", {}, what, " "),
    statusChip(job.status),
    h("progress", { value: job.done, max: Math.max(job.total, 1) }),
    h("span", { class: "muted small job-count" }, job.total ? ` ${job.done}/${job.total}` : ""),
    ACTIVE.has(job.status) ? h("button", { class: "btn small cancel-job", onclick: () => act("cancel") }, "Cancel") : null,
    RESUMABLE.has(job.status) ? h("button", { class: "btn small resume-job", onclick: () => act("resume") }, "Resume") : null,
    job.download ? h("a", { class: "btn small download-labels", href: url(job.download), download: "" }, "Download labels (.zip)") : null,
    job.error ? h("p", { class: "error small" }, job.error) : null,
  );
}

function modelCard(ctx, card, model) {
  const c = model.card;
  const v = c.validation;
  const s = c.settings || {};
  const pick = h(
    "select",
    { class: "label-sequence", "aria-label": `Sequence to label with ${model.name}` },
    ctx.state.project.sequences.map((q) => h("option", { value: q.name }, q.name)),
  );
  const folder = h("input", {
    class: "label-dataset",
    maxlength: 4096,
    placeholder: "or a sequence folder in a data root",
    "aria-label": `Sequence folder to label with ${model.name}`,
  });
  const label = async () => {
    const path = folder.value.trim();
    try {
      await post(`/projects/${ctx.projectId}/models/${model.id}/label`, path ? { dataset: path } : { sequence: pick.value });
      await refresh(ctx, card);
    } catch (err) {
      ctx.toast(err.message, "error");
    }
  };
  const scans = (part) => (c.data?.[part] || []).reduce((n, d) => n + d.scans, 0);
  return h(
    "li",
    { class: "model-card", dataset: { modelId: String(model.id) } },
    h("div", { class: "card-head" }, h("strong", { class: "model-title" }, model.name), h("span", { class: "muted small" }, fmtTime(c.written_at))),
    h(
      "p",
      { class: "small model-data" },
      `Trained on ${scans("train")} scans, validated on ${scans("validation")} (runs: ${(c.data?.runs || []).join(", ") || "none"}). `,
      `Steps ${s.steps}, ${s.points_per_scan} points per scan, seed ${s.seed}.`,
    ),
    h(
      "p",
      { class: "small model-miou" },
      v && v.scans ? `Validation mIoU ${fmtPct(v.miou)} on ${v.scans} scans` : "No validation scans (give more frames or a smaller block).",
    ),
    h(
      "table",
      { class: "small model-classes" },
      h("thead", {}, h("tr", {}, h("th", {}, "class"), h("th", {}, "export id"), h("th", {}, "training points"), h("th", {}, "val. IoU"))),
      h(
        "tbody",
        {},
        (c.classes || []).map((k) =>
          h(
            "tr",
            { dataset: { cls: k.name } },
            h("td", {}, k.name),
            h("td", {}, String(k.export_id)),
            h("td", {}, String(k.training_points)),
            h("td", {}, v && v.iou ? fmtPct(v.iou[k.name]) : "–"),
          ),
        ),
      ),
    ),
    h("div", { class: "model-label" }, pick, folder, h("button", { class: "btn small label-with-model", onclick: label }, "Label with this model")),
  );
}

async function refresh(ctx, card) {
  let jobs;
  let models;
  try {
    [jobs, models] = await Promise.all([get(`/projects/${ctx.projectId}/model-jobs`), get(`/projects/${ctx.projectId}/models`)]);
  } catch (err) {
    replace(card.querySelector(".model-lists"), h("p", { class: "error" }, err.message));
    return;
  }
  replace(
    card.querySelector(".model-lists"),
    h("h3", { class: "small" }, "Jobs"),
    jobs.count ? h("ul", { id: "model-jobs", class: "plain-list" }, jobs.data.map((j) => jobItem(ctx, card, j))) : h("p", { class: "muted small" }, "No model jobs yet."),
    h("h3", { class: "small" }, "Models"),
    models.count ? h("ul", { id: "models", class: "plain-list" }, models.data.map((m) => modelCard(ctx, card, m))) : h("p", { class: "muted small" }, "No trained model yet."),
  );
  clearTimeout(card._poll);
  if (card.isConnected && jobs.data.some((j) => ACTIVE.has(j.status))) card._poll = setTimeout(() => refresh(ctx, card), POLL_MS);
}

/** Add the models card to the page's main column and keep it current while its jobs work. */
export function mountModels(ctx) {
  const column = document.querySelector(".main-col");
  if (!column) return;
  const card = h(
    "section",
    { class: "card", id: "lidar-models" },
    h("div", { class: "card-head" }, h("h2", {}, "LiDAR-only models"), h("span", { class: "muted small" }, "trained on the latest finished run's labels")),
  );
  card.append(trainForm(ctx, card), h("div", { class: "model-lists" }));
  column.append(card);
  refresh(ctx, card);
}
