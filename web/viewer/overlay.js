// Additions to viser's client page, which the app relays under /api/v1/projects/{id}/viewer/client/ and
// loads this module into (app/api/routes/viewer.py). viser draws the scene and the panel; what its client
// cannot do (keyboard shortcuts, free-hand selection on the canvas, ...) lives in these modules and talks
// to the app's viewer routes, which act on the same server-side ReviewSession as the panel.
//
// Requests carry the leap_token cookie the client page set, so no token handling is needed here.

import { api } from "/api.js";
import { listen } from "./keys.js";
import "./nav.js";
import "./review.js";

const match = window.location.pathname.match(/\/projects\/(\d+)\/viewer\//);

/** The project this viewer page shows. */
export const projectId = match ? Number(match[1]) : null;

/** Call one of the viewer's routes, e.g. `viewerApi("POST", "scan/step", { step: 1 })`. */
export function viewerApi(method, path, body) {
  return api(method, `/projects/${projectId}/viewer/${path}`, body);
}

function addStyles() {
  const link = document.createElement("link");
  link.rel = "stylesheet";
  link.href = "/viewer/overlay.css";
  document.head.append(link);
}

async function start() {
  if (projectId === null) return;
  addStyles();
  // Feature modules bind their keys on import; listen() last, so the "?" list is complete.
  await import("./tools.js");
  listen();
}

start();
