// Reviewers of the project: this browser's reviewer name (asked once, kept in localStorage and passed to
// every 3D viewer tab opened from here, which stores it with each correction and review mark), a batch of
// the review queue claimed for that name (the other reviewers' viewers skip it), and what each reviewer did.
// Names only, no accounts (app/reviewers.py).

import { get, post } from "../api.js";
import { h, replace } from "../dom.js";
import { sequenceQuery } from "./review.js";

const NAME_KEY = "leap.reviewer";
const BATCH = 10;
const MAX_BATCH = 500;

/** This browser's reviewer name ("" until given). */
export function reviewerName() {
  return (localStorage.getItem(NAME_KEY) || "").trim();
}

function setReviewerName(name) {
  if (name) localStorage.setItem(NAME_KEY, name);
  else localStorage.removeItem(NAME_KEY);
}

/** `{ sequence }` of the sequence picked beside "Open 3D viewer" in a project of several, else `{}`. */
function sequenceBody(ctx) {
  return sequenceQuery(ctx) ? { sequence: ctx.state.viewerSequence } : {};
}

/** Mount the "Reviewers" card after the review progress and fill it. */
export async function renderReviewers(ctx) {
  const { projectId, els, toast } = ctx;
  let card = document.getElementById("reviewers");
  if (!card) {
    card = h("section", { class: "card", id: "reviewers" });
    (document.getElementById("review-progress") || els.run).after(card);
  }
  const message = h("p", { class: "muted", id: "claim-message", role: "status" });
  const name = h("input", {
    id: "reviewer-name",
    type: "text",
    maxlength: "64",
    value: reviewerName(),
    placeholder: "your name (kept in this browser)",
    onchange: (e) => {
      setReviewerName(e.target.value.trim());
      refresh();
    },
  });
  const kind = h(
    "select",
    { id: "claim-kind" },
    h("option", { value: "confidence" }, "lowest confidence queue"),
    h("option", { value: "disagreement" }, "disagreement queue"),
  );

  const count = h("input", { id: "claim-count", type: "number", min: "1", max: String(MAX_BATCH), value: String(BATCH) });

  const needName = () => {
    const who = reviewerName();
    if (!who) {
      name.focus();
      toast("Type your reviewer name first: it is kept in this browser", "error");
    }
    return who;
  };

  const claim = async () => {
    const who = needName();
    if (!who) return;
    try {
      const n = Math.min(MAX_BATCH, Math.max(1, Math.round(Number(count.value) || BATCH)));
      const body = { reviewer: who, count: n, kind: kind.value, ...sequenceBody(ctx) };
      const r = await post(`/projects/${projectId}/review/claims`, body);
      message.textContent = r.regions.length
        ? `You hold ${r.regions.length} regions for an hour; the others' viewers skip them.`
        : "No unreviewed region is left unclaimed in this queue.";
    } catch (err) {
      message.textContent = err.message;
    }
    refresh();
  };

  const release = async () => {
    const who = needName();
    if (!who) return;
    try {
      const r = await post(`/projects/${projectId}/review/claims/release`, { reviewer: who, ...sequenceBody(ctx) });
      message.textContent = `Released ${r.released} regions.`;
    } catch (err) {
      message.textContent = err.message;
    }
    refresh();
  };

  const table = h("div", { id: "reviewer-table" });

  async function refresh() {
    let data;
    try {
      data = (await get(`/projects/${projectId}/reviewers${sequenceQuery(ctx)}`)).data;
    } catch (err) {
      replace(table, h("p", { class: "error" }, err.message));
      return;
    }
    if (!data.length) {
      replace(table, h("p", { class: "muted" }, "No named reviewer has corrected, marked or claimed anything yet."));
      return;
    }
    const me = reviewerName();
    replace(
      table,
      h(
        "table",
        { class: "reviewers" },
        h("tr", {}, ...["Reviewer", "Accepted", "Skipped", "Corrections", "Claimed"].map((t) => h("th", {}, t))),
        ...data.map((r) =>
          h(
            "tr",
            { "data-reviewer": r.reviewer, class: r.reviewer === me ? "me" : "" },
            h("td", {}, r.reviewer),
            h("td", {}, String(r.accepted)),
            h("td", {}, String(r.skipped)),
            h("td", {}, String(r.corrections)),
            h("td", { class: "claimed" }, String(r.claimed)),
          ),
        ),
      ),
    );
  }

  replace(
    card,
    h("h2", {}, "Reviewers"),
    h("label", { class: "inline" }, "Reviewing as ", name),
    h(
      "p",
      {},
      h("button", { class: "btn", id: "claim-button", onclick: claim }, "Claim"),
      " ",
      count,
      " regions of the ",
      kind,
      " ",
      h("button", { class: "btn secondary", id: "release-button", onclick: release }, "Release my claims"),
    ),
    message,
    table,
  );
  await refresh();
}
