// Selection tools on the viewer page: lasso and brush drawn on a canvas over viser's, and their keys.
//
// viser's client has no lasso, brush or keyboard, so the outline is drawn here and sent to the app
// (app/api/routes/viewer_tools.py) in normalised screen coordinates; the server selects with the camera
// of the browser whose camera moved last. The drawing canvas exists only while a lasso or brush is
// armed: otherwise it would swallow the pointer and viser's orbit controls would stop working.
// Settings (armed tool, brush radius, ...) live in the server's session, shared with the panel; this
// module polls them (pollState) so a tool armed from the panel shows here too.

import { bind, notify } from "./keys.js";
import { pollState, projectId, viewerApi } from "./viewer-api.js";

const POLL_MS = 400;
let state = { tool: null, brush_radius: 0.03, classes: [] };
let overlay = null;
let stroke = null;

function viserCanvas() {
  return document.querySelector("canvas:not(#leap-tool-canvas)");
}

function setState(next) {
  state = next;
  const drawing = state.tool === "lasso" || state.tool === "brush";
  if (drawing && !overlay) makeOverlay();
  if (!drawing && overlay) {
    overlay.remove();
    overlay = null;
    stroke = null;
  }
  if (overlay) {
    overlay.dataset.tool = state.tool;
    place();
  }
}

async function patchTools(body) {
  setState(await viewerApi("PATCH", "tools", body));
}

/** Cover viser's canvas exactly, so normalised coordinates mean the same on both. */
function place() {
  const target = viserCanvas();
  if (!overlay || !target) return;
  const r = target.getBoundingClientRect();
  Object.assign(overlay.style, { left: `${r.left}px`, top: `${r.top}px`, width: `${r.width}px`, height: `${r.height}px` });
  if (overlay.width !== Math.round(r.width) || overlay.height !== Math.round(r.height)) {
    overlay.width = Math.round(r.width);
    overlay.height = Math.round(r.height);
  }
}

function makeOverlay() {
  overlay = document.createElement("canvas");
  overlay.id = "leap-tool-canvas";
  overlay.setAttribute("aria-label", "selection tool drawing area");
  document.body.append(overlay);
  place();
  overlay.addEventListener("pointerdown", (event) => {
    if (event.button !== 0) return;
    overlay.setPointerCapture(event.pointerId);
    stroke = { points: [], add: event.shiftKey };
    addPoint(event);
  });
  overlay.addEventListener("pointermove", (event) => {
    if (stroke) addPoint(event);
  });
  overlay.addEventListener("pointerup", () => finish());
  overlay.addEventListener("pointercancel", () => {
    stroke = null;
    draw();
  });
}

function addPoint(event) {
  const r = overlay.getBoundingClientRect();
  stroke.points.push([(event.clientX - r.left) / r.width, (event.clientY - r.top) / r.height]);
  draw();
}

function draw() {
  if (!overlay) return;
  const ctx = overlay.getContext("2d");
  ctx.clearRect(0, 0, overlay.width, overlay.height);
  if (!stroke || !stroke.points.length) return;
  const w = overlay.width;
  const h = overlay.height;
  ctx.beginPath();
  stroke.points.forEach(([u, v], i) => (i ? ctx.lineTo(u * w, v * h) : ctx.moveTo(u * w, v * h)));
  if (state.tool === "lasso") {
    ctx.closePath();
    ctx.fillStyle = "rgba(255, 200, 0, 0.15)";
    ctx.fill();
    ctx.strokeStyle = "rgba(255, 200, 0, 0.95)";
    ctx.lineWidth = 2;
  } else {
    ctx.strokeStyle = "rgba(255, 200, 0, 0.45)";
    ctx.lineWidth = 2 * state.brush_radius * h;
    ctx.lineCap = "round";
    ctx.lineJoin = "round";
  }
  ctx.stroke();
}

async function finish() {
  if (!stroke) return;
  const { points, add } = stroke;
  stroke = null;
  const tool = state.tool;
  const enough = tool === "lasso" ? points.length >= 3 : points.length >= 1;
  try {
    if (!enough) return;
    const res = await viewerApi("POST", "tools/select", { tool, points, add });
    notify(`${res.count.toLocaleString()} ${res.target === "scan" ? "points" : "voxels"} selected`);
  } finally {
    draw();
  }
}

async function arm(tool) {
  await patchTools({ tool: state.tool === tool ? "none" : tool });
  notify(state.tool ? `${state.tool} armed: drag on the view` : "tool off: the camera orbits");
}

async function assign(body) {
  const res = await viewerApi("POST", "tools/assign", body);
  if (res.correction_id === null) notify("Nothing selected", "error");
  else notify(body.erase ? "Erased to unlabeled" : `Assigned ${state.classes[body.slot - 1] || "class"}`);
}

async function poll() {
  if (!stroke) setState(await viewerApi("GET", "tools"));
}

// Classes past the ninth: type the number ("1" "2" for the 12th; "0" alone is the 10th). A digit waits
// DIGIT_WAIT_MS for the next one only while a longer number could still name a class, so with nine classes
// or fewer every digit assigns at once.
const DIGIT_WAIT_MS = 700;
let digits = "";
let digitTimer = null;

function slotOf(typed) {
  return typed === "0" ? 10 : Number(typed);
}

function assignTyped() {
  clearTimeout(digitTimer);
  digitTimer = null;
  const slot = slotOf(digits);
  digits = "";
  if (slot >= 1 && slot <= state.classes.length) assign({ slot });
  else notify(`No class ${slot}: the picker has ${state.classes.length}`, "error");
}

function digitKey(event) {
  digits += event.key;
  clearTimeout(digitTimer);
  if (digits !== "0" && slotOf(digits) * 10 <= state.classes.length) digitTimer = setTimeout(assignTyped, DIGIT_WAIT_MS);
  else assignTyped();
}

bind(["1", "2", "3", "4", "5", "6", "7", "8", "9", "0"], "Assign the n-th class of the picker to the selection (type 1 2 for the 12th, 0 for the 10th)",
  digitKey, "Selection and corrections", ["1-9", "0"]);
bind(["e"], "Erase the selection to unlabeled", () => assign({ erase: true }), "Selection and corrections");
bind(["ctrl+z"], "Undo the last correction", () => viewerApi("POST", "tools/undo", {}), "Selection and corrections");
bind(["ctrl+shift+z"], "Redo", () => viewerApi("POST", "tools/redo", {}), "Selection and corrections");
bind(["l"], "Lasso (drag a free outline; Shift adds)", () => arm("lasso"), "Selection and corrections");
bind(["b"], "Brush (paint while dragging; Shift adds)", () => arm("brush"), "Selection and corrections");
bind(["m"], "Box (drag a rectangle)", () => arm("box"), "Selection and corrections");
bind(["["], "Smaller brush", () => patchTools({ brush_radius: Math.max(0.005, state.brush_radius / 1.25) }),
  "Selection and corrections");
bind(["]"], "Larger brush", () => patchTools({ brush_radius: Math.min(0.5, state.brush_radius * 1.25) }),
  "Selection and corrections");
bind(["escape"], "Clear the selection and put the tool down", async () => {
  setState(await viewerApi("POST", "tools/clear", {}));
}, "Selection and corrections");

window.addEventListener("resize", place);
if (projectId !== null) pollState(poll, POLL_MS);
