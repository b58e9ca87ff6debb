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
