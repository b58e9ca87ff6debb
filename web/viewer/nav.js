// Scan navigation keys of the 3D viewer, and the enlarged scan image.
//
// Keys call app/api/routes/viewer_nav.py, which acts on the same server-side session as the panel's
// Browse / Fit view / Follow ego / Enlarge image widgets. The enlarged image is an <img> over the canvas
// (viser's panel image is a thumbnail); the page polls the viewer's state so that the image follows every
// scan change (keys, panel slider, play) and opens or closes from the panel's button too (pollState: at
// POLL_MS while the page is in use or playing, rarely while idle).

import { bind, notify } from "./keys.js";
import { pollState, projectId, viewerApi } from "./viewer-api.js";

const GROUP = "Scans and camera";
const POLL_MS = 800;

let state = null;
let shownPos = null;

function imageBox() {
  let box = document.getElementById("leap-image");
  if (!box) {
    box = document.createElement("div");
    box.id = "leap-image";
    box.hidden = true;
    const img = document.createElement("img");
    img.alt = "Camera image of the shown scan with its labels";
    const caption = document.createElement("p");
    caption.className = "leap-image-caption";
    box.append(img, caption);
    box.addEventListener("click", () => act("POST", "nav/image", { on: false }));
    document.body.append(box);
  }
  return box;
}

/** Lay the image box over the canvas, full canvas width (the panel docked on the right stays free). */
function placeImage(box) {
  const canvas = document.querySelector("canvas");
  if (!canvas) return;
  const r = canvas.getBoundingClientRect();
  box.style.left = `${r.left}px`;
  box.style.width = `${r.width}px`;
  box.style.bottom = `${Math.max(0, window.innerHeight - r.bottom)}px`;
}

function render() {
  const box = imageBox();
  const open = Boolean(state && state.image_open && state.has_image);
  box.hidden = !open;
  if (!open) return;
  placeImage(box);
  const shown = `${state.pos}/${state.camera}/${state.zoomed ? "zoomed" : ""}`;
  if (shownPos !== shown) {
    shownPos = shown;
    // The query only defeats the browser cache; the route always serves the shown scan's chosen camera
    // (the focused review region's zoomed crop while one is focused in it).
    const query = new URLSearchParams({
      pos: String(state.pos),
      camera: String(state.camera),
      z: state.zoomed ? "1" : "0",
    });
    box.querySelector("img").src = `/api/v1/projects/${projectId}/viewer/nav/image?${query}`;
  }
  const where = `Scan ${state.frame_id} (${state.pos + 1}/${state.count}), camera ${state.camera}`;
  box.querySelector(".leap-image-caption").textContent = state.zoomed
    ? `${where}, zoomed on the review region. Press I or click to close.`
    : `${where}. Press I or click to close.`;
}

async function act(method, path, body) {
  state = await viewerApi(method, path, body);
  render();
  return state;
}

async function poll() {
  state = await viewerApi("GET", "nav");
  render();
}

bind(["arrowright", "."], "Next scan", () => act("POST", "nav/step", { step: 1 }), GROUP);
bind(["arrowleft", ","], "Previous scan", () => act("POST", "nav/step", { step: -1 }), GROUP);
bind([" "], "Play / pause through the scans", async () => {
  const s = await act("POST", "nav/play", { on: null });
  notify(s.playing ? "Playing through the scans" : "Paused");
}, GROUP);
bind(["f"], "Fit the view to the shown scan", () => act("POST", "nav/fit", { target: "scan" }), GROUP);
bind(["shift+f"], "Fit the view to the whole map", () => act("POST", "nav/fit", { target: "map" }), GROUP);
bind(["g"], "Camera follows the ego vehicle on scan changes (on/off)", async () => {
  const s = await act("POST", "nav/follow", { on: null });
  notify(s.follow ? "Camera follows the ego vehicle" : "Camera stays where it is");
}, GROUP);
bind(["i"], "Enlarge / shrink the scan's camera image", async () => {
  const s = await act("POST", "nav/image", { on: null });
  if (s.image_open && !s.has_image) notify("This scan has no camera image", "error");
}, GROUP);
window.addEventListener("resize", () => render());

if (projectId !== null) pollState(poll, POLL_MS, () => Boolean(state && state.playing));
