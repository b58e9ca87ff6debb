// Entry point: token capture, a tiny hash router (#/ and #/projects/<id>) and the toast line.

import { ApiError, captureToken, get, setToken, token } from "./api.js";
import { h, replace } from "./dom.js";
import { renderProject } from "./project.js";
import { renderProjects } from "./projects.js";

const app = document.getElementById("app");
let current = null; // the mounted view's cleanup function

export function toast(message, kind = "info") {
  const el = document.getElementById("toast");
  el.textContent = message;
  el.className = `toast ${kind}`;
  el.hidden = false;
  clearTimeout(toast.timer);
  toast.timer = setTimeout(() => (el.hidden = true), kind === "error" ? 8000 : 3500);
}

/** `refused`: a token was sent and the server answered 403, so the user learns that one was wrong. */
function tokenForm(retry, refused) {
  const input = h("input", { type: "password", placeholder: "access token", autocomplete: "off", id: "token-input" });
  return h(
    "section",
    { class: "card narrow" },
    h("h2", {}, "Access token required"),
    h("p", { class: "muted" }, "This server only answers requests that carry its access token."),
    refused
      ? h("p", { class: "error", id: "token-refused" }, "The server refused that token: use the one its `leap serve` was given (--token, --new-token or LEAP_ACCESS_TOKEN).")
      : null,
    h(
      "form",
      {
        class: "row",
        onsubmit: (e) => {
          e.preventDefault();
          setToken(input.value.trim());
          retry();
        },
      },
      input,
      h("button", { class: "btn primary", type: "submit" }, "Continue"),
    ),
  );
}

async function route() {
  if (current) current();
  current = null;
  const hash = window.location.hash || "#/";
  const m = hash.match(/^#\/projects\/(\d+)/);
  try {
    await get("/health");
  } catch (err) {
    if (err instanceof ApiError && err.status === 403) {
      replace(app, tokenForm(route, Boolean(token())));
      return;
    }
    replace(app, h("section", { class: "card" }, h("p", { class: "error" }, `Server unreachable: ${err.message}`)));
    return;
  }
  if (m) current = await renderProject(app, Number(m[1]), { toast });
  else current = await renderProjects(app, { toast });
}

captureToken();
window.addEventListener("hashchange", route);
route();
