// The viewer page's link to the app: which project it shows and how to call the viewer's routes.
//
// Every feature module of the page (nav.js, review.js, tools.js) imports these from here, and overlay.js
// imports the feature modules: no module imports the one that imports it, so each module's body runs after
// everything it reads is set.

import { api } from "/api.js";

const match = window.location.pathname.match(/\/projects\/(\d+)\/viewer\//);

/** The project this viewer page shows (null outside a viewer page). */
export const projectId = match ? Number(match[1]) : null;

const tabMatch = window.location.pathname.match(/\/viewer\/tabs\/([A-Za-z0-9_-]+)\//);

/** This browser tab's viewer session (each tab has its own scan, camera, selection and focus). */
export const tabId = tabMatch ? tabMatch[1] : null;

/** Path of one of this tab's viewer routes under /api/v1. (A plain link from this page, such as the scan
 * image, names its tab by the page it is on: the app reads the Referer.) */
export function viewerPath(path) {
  const tab = tabId ? `${path.includes("?") ? "&" : "?"}tab=${tabId}` : "";
  return `/projects/${projectId}/viewer/${path}${tab}`;
}

/** Call one of this tab's viewer routes, e.g. `viewerApi("POST", "nav/step", { step: 1 })`. */
export function viewerApi(method, path, body) {
  return api(method, viewerPath(path), body);
}

// What the page polls (nav.js: the shown scan, tools.js: the armed tool) changes only through this page
// (its keys, its panel) or while playing, so it is polled at the module's own rate for ACTIVE_MS after a
// key, click or wheel on the page, every IDLE_MS otherwise (a run that loads meanwhile), and not at all
// while the page is hidden: an idle tab's polls were a steady load on the server for every open tab.
const ACTIVE_MS = 3000;
const IDLE_MS = 15000;
let lastInput = performance.now();
const wakers = [];

function wakeAll() {
  for (const wake of wakers) wake();
}

for (const type of ["keydown", "pointerdown", "wheel"]) {
  window.addEventListener(
    type,
    () => {
      lastInput = performance.now();
      wakeAll();
    },
    { capture: true, passive: true },
  );
}
document.addEventListener("visibilitychange", () => {
  if (!document.hidden) wakeAll();
});

/** Call `tick` (async) now and then every `fastMs` while the page is in use or `busy()` says so (e.g.
 * playing), every IDLE_MS while idle, never while hidden. A tick that throws is tried again later. */
export function pollState(tick, fastMs, busy = () => false) {
  let timer = null;
  let inFlight = false;
  let fast = true;
  async function run() {
    clearTimeout(timer);
    timer = null;
    if (inFlight || document.hidden) return; // the running tick schedules the next; visibility wakes it
    inFlight = true;
    try {
      await tick();
    } catch {
      // No run loaded yet, or the viewer is restarting: try again on the next tick.
    }
    inFlight = false;
    fast = busy() || performance.now() - lastInput < ACTIVE_MS;
    timer = setTimeout(run, fast ? fastMs : IDLE_MS);
  }
  wakers.push(() => {
    // Input: back to the fast rate from now (the click's effect reaches the server a moment later).
    if (inFlight || (fast && timer !== null)) return;
    clearTimeout(timer);
    timer = setTimeout(run, fastMs);
  });
  run();
}
