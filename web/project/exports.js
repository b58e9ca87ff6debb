// A finished run's export dialog: how many points stay unlabeled and why, the stand-alone zip download,
// and writing each sequence's .label files into its dataset's predictions/ folder after an explicit
// confirmation (a second, louder one when files are already there: they are only replaced with overwrite).

import { ApiError, get, post, url } from "../api.js";
import { h, replace } from "../dom.js";

const fmt = (n) => Number(n).toLocaleString("en-US");
const pct = (n, total) => (total ? `${((100 * n) / total).toFixed(1)} %` : "0 %");

/** The export actions of a run (none until the run has exported labels). */
export function exportActions(ctx, run) {
  if (!run.has_export) return [];
  return [
    h("button", { class: "btn small", dataset: { action: "export" }, onclick: () => openExportDialog(ctx, run) }, "Export…"),
  ];
}

function countsSection(info) {
  const rows = info.reasons.map((r) =>
    h(
      "li",
      { dataset: { reason: r.key } },
      h("strong", { class: "reason-count" }, fmt(r.points)),
      ` ${r.label} (${pct(r.points, info.points)})`,
      h("div", { class: "muted small" }, r.explanation),
    ),
  );
  return h(
    "section",
    { class: "export-counts" },
    h(
      "p",
      {},
      h("strong", { class: "labeled-count" }, fmt(info.labeled)),
      ` of ${fmt(info.points)} points in ${fmt(info.frames)} scans are labeled (${pct(info.labeled, info.points)}); `,
      h("strong", { class: "unlabeled-count" }, fmt(info.unlabeled)),
      " stay unlabeled (id 0):",
    ),
    h("ul", { class: "reasons" }, rows),
    h("p", { class: "muted small threshold-note" }, info.threshold_note),
    (info.provenance_lines || []).length
      ? h("details", { class: "provenance small" }, h("summary", {}, "Where the labels came from"), h("ul", {}, info.provenance_lines.map((line) => h("li", {}, line))))
      : null,
  );
}

function zipSection(run, info) {
  const conf = h("input", { type: "checkbox", class: "zip-conf" });
  const link = h("a", { class: "btn small primary", href: url(`/runs/${run.id}/export.zip`), download: "", dataset: { action: "zip" } }, "Download .zip");
  conf.addEventListener("change", () => {
    link.setAttribute("href", url(`/runs/${run.id}/export.zip${conf.checked ? "?confidence=true" : ""}`));
  });
  return h(
    "section",
    {},
    h("h3", {}, "Download"),
    h(
      "p",
      { class: "muted small" },
      `${fmt(info.frames)} .label files in sequences/<seq>/predictions/ (SemanticKITTI layout), label-map.yaml `,
      "(semantic-kitti-api layout: ids, names, BGR colours, counts) and summary.yaml (project, run, settings, counts).",
    ),
    h("label", { class: "small" }, conf, " include .conf confidences"),
    " ",
    link,
  );
}

function writeSection(ctx, run, info, dialog) {
  const box = h("div", { class: "write-step" });
  const conf = h("input", { type: "checkbox", class: "write-conf" });
  const start = h("button", { class: "btn small", dataset: { action: "predictions" }, disabled: !info.predictions_allowed }, "Write to predictions/…");

  const ask = () => {
    const existing = info.targets.reduce((sum, t) => sum + t.existing, 0);
    const n = conf.checked ? 2 * info.frames : info.frames;
    const where = info.targets.length === 1 ? info.targets[0].path : `the ${info.targets.length} sequences' predictions/ folders`;
    const question = existing
      ? h(
          "p",
          { class: "confirm-text warn" },
          `${where} already ${info.targets.length === 1 ? "holds" : "hold"} ${fmt(existing)} files. Replace them with this run's ${fmt(n)} files? The old files are deleted.`,
        )
      : h("p", { class: "confirm-text" }, `Write ${fmt(n)} files into ${where}?`);
    const yes = h(
      "button",
      { class: existing ? "btn small danger" : "btn small primary", dataset: { action: "confirm-write" } },
      existing ? `Replace ${fmt(existing)} files` : "Write",
    );
    const no = h("button", { class: "btn small ghost", dataset: { action: "cancel-write" }, onclick: () => replace(box) }, "Cancel");
    yes.addEventListener("click", async () => {
      yes.disabled = true;
      try {
        const res = await post(`/runs/${run.id}/export`, { include_confidence: conf.checked, overwrite: existing > 0 });
        const shown = info.targets.length === 1 ? res.path : `the ${info.targets.length} sequences' predictions/ folders`;
        replace(box, h("p", { class: "write-result" }, `Wrote ${fmt(res.files)} files to ${shown}` + (res.replaced ? ` (replaced ${fmt(res.replaced)}).` : ".")));
        info.targets = (await get(`/runs/${run.id}/export`)).targets;
        ctx.toast(`Wrote ${res.files} files to ${res.path}`);
      } catch (err) {
        // 409: the folder changed since the dialog opened; show the server's reason and ask again.
        replace(box, h("p", { class: "error write-error" }, err.message));
        if (err instanceof ApiError && err.status === 409) {
          Object.assign(info, await get(`/runs/${run.id}/export`));
        }
      }
    });
    replace(box, question, yes, " ", no);
  };
  start.addEventListener("click", ask);
  return h(
    "section",
    {},
    h("h3", {}, "Write into the dataset"),
    h(
      "ul",
      { class: "muted small export-targets", id: "export-targets" },
      info.targets.map((t) => h("li", { dataset: { sequence: t.sequence } }, info.targets.length > 1 ? `${t.sequence}: ${t.path}` : t.path)),
    ),
    info.predictions_allowed ? null : h("p", { class: "muted small" }, "These folders cannot receive exports."),
    h("label", { class: "small" }, conf, " with .conf files"),
    " ",
    start,
    box,
  );
}

/** Open the export dialog of a finished run (a modal <dialog>, removed when closed). */
export async function openExportDialog(ctx, run) {
  const body = h("div", { class: "export-body" }, h("p", { class: "muted" }, "Counting points…"));
  const close = h("button", { class: "btn small ghost", dataset: { action: "close" } }, "Close");
  const dialog = h("dialog", { class: "export-dialog", "aria-label": `Export of run ${run.number}` }, h("h2", {}, `Export run ${run.number}`), body, h("div", { class: "dialog-foot" }, close));
  close.addEventListener("click", () => dialog.close());
  dialog.addEventListener("close", () => dialog.remove());
  document.body.append(dialog);
  dialog.showModal();
  try {
    const info = await get(`/runs/${run.id}/export`);
    replace(body, countsSection(info), zipSection(run, info), writeSection(ctx, run, info, dialog));
  } catch (err) {
    replace(body, h("p", { class: "error" }, err.message));
  }
}
