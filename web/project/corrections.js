// The project's manual corrections (made in the 3D viewer or through the API): counts per class, each
// correction with its scope (voxel map, one scan, or one object: where it lands in the latest run), author and time, an active toggle (undo / redo), and
// the state of the "apply corrections" job that brings the latest finished run's export up to date
// without a run. Mounted by web/project.js; polls while the page shows it. Every user string (class names,
// authors) goes in as text (dom.js h), never as HTML.

import { get, patch, post } from "../api.js";
import { fmtTime, h, replace } from "../dom.js";
import { sequenceQuery } from "./review.js";
import { openViewer } from "./viewer.js";

const POLL_MS = 2000;

function className(c) {
  // A merge or a split of objects assigns no class.
  if (c.action === "merge") return `merge of objects ${c.track_id} and ${c.other_track_id}`;
  if (c.action === "split") return `split of object ${c.track_id} at scan ${c.split_frame}`;
  return c.class_name === "" ? "erase (unlabeled)" : c.class_name;
}

function scopeText(c) {
  if (c.scope === "scan") return `scan ${c.frame_id}`;
  if (c.scope === "object") return `object ${c.track_id} of run id ${c.run_id}`;
  return "map";
}

function objectsText(m) {
  if (m.other_track != null) return `objects ${m.other_track} into ${m.track}`;
  if (m.new_track) return `object ${m.track}, new object ${m.new_track}`;
  return `object ${m.track}`;
}

// Where an object correction lands in the latest finished run (docs/METHOD.md B.6, object corrections).
function sizeText(c, latestRunObjects) {
  if (c.scope === "scan") return `${c.points} points`;
  if (c.scope !== "object") return `${c.voxels} voxels`;
  const m = c.match;
  // The latest run tracked no objects (tracking off): the correction waits for a run that does.
  if (!m && latestRunObjects === false) return "latest run has no objects (tracking off): changes nothing yet";
  if (!m) return "not applied yet";
  if (!m.applied) {
    const iou = Math.min(m.iou, m.other_iou ?? m.iou);
    if (m.track && m.track === m.other_track) return `run ${m.run_number}: the two are already one object: changes nothing`;
    if (m.new_track === 0 && m.iou > 0.5) return `run ${m.run_number}: scan not labeled in this run: changes nothing`;
    return `run ${m.run_number}: no longer matches an object (best IoU ${iou.toFixed(2)}): changes nothing`;
  }
  return `run ${m.run_number}: ${objectsText(m)} (IoU ${m.iou.toFixed(2)})`;
}

function applyText(a) {
  if (a.status === "running") return "Applying corrections to the latest run's export…";
  if (a.status === "failed") return `Applying corrections failed: ${a.error || "unknown error"}`;
  if (a.status === "no_run") return "No finished run yet: corrections apply at the next run.";
  if (a.status === "done") {
    if (!a.frames && !a.baked_reverts) return `Run ${a.run_number}'s export is up to date: no scan needed a change.`;
    const reverts = a.baked_reverts ? ` ${a.baked_reverts} undone voxels keep their class until the next run.` : "";
    return `Applied to run ${a.run_number}: ${a.frames} scan${a.frames === 1 ? "" : "s"} updated in ${a.seconds.toFixed(2)} s.${reverts}`;
  }
  return "Corrections made now reach the latest run's export at once.";
}

export function mountCorrections(ctx) {
  const el = h("section", { class: "card", id: "corrections" });
  const anchor = ctx.els.runs;
  anchor.parentElement.insertBefore(el, anchor);
  let timer = null;
  let lastApplied; // undefined until the first answer

  async function toggle(c, active) {
    try {
      await patch(`/projects/${ctx.projectId}/corrections/${c.id}`, { active });
    } catch (err) {
      ctx.toast(err.message, "error");
    }
    await render();
  }

  async function render() {
    if (!el.isConnected) return;
    let body;
    try {
      body = await get(`/projects/${ctx.projectId}/corrections${sequenceQuery(ctx)}`);
    } catch (err) {
      replace(el, h("h2", {}, "Corrections"), h("p", { class: "error" }, err.message));
      return;
    }
    const applied = body.apply.status === "done" ? `${body.apply.run_id}@${body.apply.finished_at}` : null;
    if (applied && lastApplied !== undefined && applied !== lastApplied) {
      // That run's export changed: its cached metrics no longer say whether they predate the corrections.
      ctx.state.metrics.delete(body.apply.run_id);
      ctx.render.compare();
    }
    lastApplied = applied;
    const canShow = Boolean(ctx.state.health && ctx.state.health.viewer && ctx.state.runs.some((r) => r.status === "done"));
    const rows = body.corrections.map((c) =>
      h(
        "tr",
        { dataset: { id: String(c.id) }, class: c.active ? "" : "muted" },
        h("td", {}, className(c)),
        h("td", {}, scopeText(c)),
        h("td", { class: c.scope === "object" ? "corr-match" : "num" }, sizeText(c, body.latest_run_objects)),
        h("td", {}, c.author || "—"),
        h("td", {}, fmtTime(c.created_at)),
        h(
          "td",
          {},
          h("input", {
            type: "checkbox",
            class: "corr-active",
            checked: c.active,
            "aria-label": `Correction ${c.id} active`,
            onchange: (e) => toggle(c, e.target.checked),
          }),
        ),
        canShow && c.scope !== "object"
          ? h(
              "td",
              {},
              h(
                "button",
                {
                  class: "btn small corr-show",
                  title: "Open the 3D viewer with this correction selected and in view",
                  "aria-label": `Show correction ${c.id} in 3D`,
                  onclick: () =>
                    // The new tab (v.tab) is the one that shows it, not another viewer tab already open.
                    openViewer(ctx, (v) =>
                      post(`/projects/${ctx.projectId}/viewer/tools/corrections/${c.id}/show?tab=${v.tab}`),
                    ),
                },
                "Show in 3D",
              ),
            )
          : canShow
            ? h("td", {})
            : null,
      ),
    );
    replace(
      el,
      h("div", { class: "card-head" }, h("h2", {}, "Corrections"), h("span", { class: "muted small", id: "corrections-apply", dataset: { status: body.apply.status } }, applyText(body.apply))),
      body.per_class.length
        ? h(
            "ul",
            { class: "corr-classes" },
            body.per_class.map((p) => h("li", { dataset: { cls: p.class_name } }, `${className({ class_name: p.class_name })}: ${p.corrections} correction${p.corrections === 1 ? "" : "s"}, ${p.voxels} voxels`)),
          )
        : null,
      rows.length
        ? h(
            "table",
            { class: "corr-table" },
            h("thead", {}, h("tr", {}, ["Class", "Scope", "Size", "By", "When", "Active", ...(canShow ? [""] : [])].map((t) => h("th", {}, t)))),
            h("tbody", {}, rows),
          )
        : h("p", { class: "muted small" }, "No corrections yet. Make them in the 3D viewer (select, then a class)."),
    );
  }

  ctx.render.corrections = render;

  async function loop() {
    if (!el.isConnected) return;
    await render();
    timer = setTimeout(loop, POLL_MS);
  }
  loop();
  return () => clearTimeout(timer);
}
