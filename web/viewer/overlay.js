// Additions to viser's client page, which the app relays under
// /api/v1/projects/{id}/viewer/tabs/{tab}/client/ (one viser server per browser tab) and loads this module
// into (app/api/routes/viewer.py). viser draws the scene and the panel; what its client cannot do (keyboard
// shortcuts, free-hand selection on the canvas, ...) lives in these modules and talks to the app's viewer
// routes (viewer-api.js), which act on this tab's server-side ReviewSession, as its panel does.
//
// Requests carry the leap_token cookie the client page set, so no token handling is needed here.

import { listen } from "./keys.js";
import "./nav.js";
import "./review.js";
import "./tools.js";
import { projectId } from "./viewer-api.js";

function addStyles() {
  const link = document.createElement("link");
  link.rel = "stylesheet";
  link.href = "/viewer/overlay.css";
  document.head.append(link);
}

if (projectId !== null) {
  addStyles();
  // Feature modules bound their keys on import; listen() last, so the "?" list is complete.
  listen();
}
