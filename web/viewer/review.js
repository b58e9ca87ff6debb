// Review queue keys on the viewer page: a accept, s skip, r relabel (class picker), n / p next / previous,
// Esc leave the review.
//
// Each key calls app/api/routes/viewer_review.py, which acts on the same server-side ReviewSession as the
// panel's "Review queue" buttons: the session highlights the region (the rest of the map dims), frames the
// camera, jumps the scan slider to the scan that saw the region most and boxes the region in its image.
// A small badge shows the progress ("12 / 100 reviewed"), a busy sign while a queue is being ranked, and,
// while a region is highlighted, a "Leave review" button (as Esc) that undims the map.

import { bind, notify } from "./keys.js";
import { projectId, viewerApi } from "./viewer-api.js";

const GROUP = "Review queue";
let badge = null;
let busy = false;

// A page that loads (a reload, a second tab) starts out of the review: the focus lives in the server's
// session, and a dimmed map with no badge or button to leave it would be a trap. The progress shows at once
// (a viewer reopened after a restart shows the stored marks). Queue actions wait for this, so a quick N
// is not undone by it.
const started = projectId === null ? Promise.resolve() : viewerApi("POST", "review/leave", {})
  .then((state) => { if (state.total) show(state); })
  .catch(() => {});

function ensureBadge() {
  if (badge) return badge;
  badge = document.createElement("div");
  badge.id = "leap-review";
  badge.setAttribute("role", "status");
  badge.hidden = true;
  document.body.append(badge);
  return badge;
}

/** Show the queue's state (progress and the highlighted region) in the badge. */
function show(state) {
  const el = ensureBadge();
  el.replaceChildren();
  el.dataset.busy = state.building ? "1" : "";
  const progress = document.createElement("span");
  progress.className = "leap-review-progress";
  progress.textContent = state.progress;
  el.append(progress);
  if (state.region) {
    const r = state.region;
    const where = document.createElement("span");
    where.className = "leap-review-region";
    const seen = r.frame_id ? `, scan ${r.frame_id}` : "";
    where.textContent = ` · region ${r.position + 1}/${state.total} (${r.state || "not reviewed"}${seen})`;
    const leaveButton = document.createElement("button");
    leaveButton.type = "button";
    leaveButton.className = "leap-review-leave";
    leaveButton.textContent = "Leave review (Esc)";
    leaveButton.title = "Undim the map and remove the region's box; N goes on from this region";
    leaveButton.addEventListener("click", () => leave().catch((err) => notify(err.message || String(err), "error")));
    el.append(where, leaveButton);
  }
  el.hidden = false;
}

function setBusy(on, text) {
  busy = on;
  const el = ensureBadge();
  el.dataset.busy = on ? "1" : "";
  if (on) {
    el.replaceChildren();
    const spin = document.createElement("span");
    spin.className = "leap-spinner";
    el.append(spin, document.createTextNode(` ${text}`));
    el.hidden = false;
  }
}

let acting = Promise.resolve();

/** Run one queue action with the busy sign up (ranking the disagreement queue reads every scan). */
function act(path, body, text) {
  if (busy) return null;
  setBusy(true, text);
  const run = (async () => {
    try {
      await started;
      const state = await viewerApi("POST", `review/${path}`, body);
      setBusy(false);
      show(state);
      return state;
    } catch (err) {
      setBusy(false);
      throw err;
    }
  })();
  acting = run.catch(() => {});
  return run;
}

/** Leave the review: the server undims the map and removes the region's box (the queue stays). */
async function leave() {
  const state = await viewerApi("POST", "review/leave", {});
  if (state.total || !ensureBadge().hidden) show(state);
  return state;
}

function closePicker() {
  const el = document.getElementById("leap-review-picker");
  if (!el) return false;
  el.remove();
  return true;
}

/** The class picker for `r`: a list of the run's classes; picking one relabels the highlighted region. */
async function openPicker() {
  closePicker();
  const state = await viewerApi("GET", "review");
  if (!state.region) {
    notify("No region is highlighted: press N first.", "error");
    return;
  }
  const box = document.createElement("div");
  box.id = "leap-review-picker";
  box.setAttribute("role", "dialog");
  box.setAttribute("aria-label", "Relabel region as");
  const title = document.createElement("h2");
  title.textContent = `Relabel region ${state.region.position + 1} (${state.region.count} voxels) as`;
  box.append(title);
  state.classes.forEach((name) => {
    const b = document.createElement("button");
    b.type = "button";
    b.textContent = name;
    b.addEventListener("click", async () => {
      closePicker();
      try {
        await act("relabel", { class_name: name }, "Relabelling…");
        notify(`Region relabelled as ${name} and accepted.`);
      } catch (err) {
        notify(err.message || String(err), "error");
      }
    });
    box.append(b);
  });
  const cancel = document.createElement("button");
  cancel.type = "button";
  cancel.className = "leap-cancel";
  cancel.textContent = "Cancel (Esc)";
  cancel.addEventListener("click", closePicker);
  box.append(cancel);
  document.body.append(box);
}

window.addEventListener("keydown", (ev) => {
  // Esc on an open picker only closes it; the other Esc bindings (leave the review, put the tool down)
  // wait for the next press. This listener is added before keys.js's, so it can stop theirs.
  if (ev.key === "Escape" && closePicker()) ev.stopImmediatePropagation();
}, true);

bind(["a"], "Accept the highlighted region (mark reviewed) and go to the next", () =>
  act("mark", { state: "accepted" }, "Saving…"), GROUP);
bind(["s"], "Skip the highlighted region and go to the next", () =>
  act("mark", { state: "skipped" }, "Saving…"), GROUP);
bind(["r"], "Relabel the highlighted region (class picker)", openPicker, GROUP);
bind(["n"], "Next review region (ranks the queue first)", () =>
  act("step", { step: 1 }, "Ranking regions…"), GROUP);
bind(["p"], "Previous review region", () => act("step", { step: -1 }, "Ranking regions…"), GROUP);
// Esc during a step (the queue may take seconds to rank) leaves the region that step shows: never dropped.
bind(["escape"], "Leave the review (undim the map; N goes on from the last region)",
  () => acting.then(leave), GROUP);

// The badge exists (hidden) from the start: tests wait for it to know the keys are bound.
ensureBadge();

