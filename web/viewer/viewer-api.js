// The viewer page's link to the app: which project it shows and how to call the viewer's routes.
//
// Every feature module of the page (nav.js, review.js, tools.js) imports these from here, and overlay.js
// imports the feature modules: no module imports the one that imports it, so each module's body runs after
// everything it reads is set.

import { api } from "/api.js";

const match = window.location.pathname.match(/\/projects\/(\d+)\/viewer\//);

/** The project this viewer page shows (null outside a viewer page). */
export const projectId = match ? Number(match[1]) : null;

/** Call one of the viewer's routes, e.g. `viewerApi("POST", "nav/step", { step: 1 })`. */
export function viewerApi(method, path, body) {
  return api(method, `/projects/${projectId}/viewer/${path}`, body);
}
