// Thin client for the REST API under /api/v1. The access token (when the server requires one) is taken
// once from the page URL (?token=...), kept in sessionStorage and sent as a header; EventSource streams
// and download links, which cannot set headers, carry it as a query parameter.

const BASE = "/api/v1";
const TOKEN_KEY = "leap_token";

export class ApiError extends Error {
  constructor(status, detail) {
    super(errorText(detail) || `HTTP ${status}`);
    this.status = status;
    this.detail = detail;
  }

  /** The first field name of a 422 answer (e.g. "threshold" for loc [body, form, threshold]). */
  field() {
    if (!Array.isArray(this.detail) || !this.detail.length) return null;
    const loc = this.detail[0].loc || [];
    return loc.length ? String(loc[loc.length - 1]) : null;
  }
}

export function errorText(detail) {
  if (detail === null || detail === undefined) return "";
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) {
    return detail
      .map((d) => {
        const loc = (d.loc || []).filter((p) => p !== "body").join(".");
        // Some messages name their field already (an uploaded file's "classes[3].prompts: ...").
        return loc && !String(d.msg).startsWith(`${loc}: `) ? `${loc}: ${d.msg}` : d.msg;
      })
      .join("; ");
  }
  return JSON.stringify(detail);
}

export function captureToken() {
  const params = new URLSearchParams(window.location.search);
  const t = params.get("token");
  if (t) {
    sessionStorage.setItem(TOKEN_KEY, t);
    params.delete("token");
    const rest = params.toString();
    history.replaceState(null, "", window.location.pathname + (rest ? `?${rest}` : "") + window.location.hash);
  }
}

export function token() {
  return sessionStorage.getItem(TOKEN_KEY);
}

export function setToken(t) {
  if (t) sessionStorage.setItem(TOKEN_KEY, t);
  else sessionStorage.removeItem(TOKEN_KEY);
}

/** URL under /api/v1 with the token appended (for EventSource, links and window.open). */
export function url(path) {
  const t = token();
  const full = path.startsWith("/api/") ? path : BASE + path;
  if (!t) return full;
  return full + (full.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(t);
}

/** `contentType`: send `body` as it is (a file's bytes) under that type instead of as JSON. */
export async function api(method, path, body, contentType) {
  const headers = { Accept: "application/json" };
  const t = token();
  if (t) headers["X-Leap-Token"] = t;
  const init = { method, headers };
  if (body !== undefined) {
    headers["Content-Type"] = contentType || "application/json";
    init.body = contentType ? body : JSON.stringify(body);
  }
  const res = await fetch(BASE + path, init);
  if (!res.ok) {
    let detail = res.statusText;
    try {
      detail = (await res.json()).detail;
    } catch (_) {
      /* not JSON */
    }
    throw new ApiError(res.status, detail);
  }
  if (res.status === 204) return null;
  return res.json();
}

export const get = (path) => api("GET", path);
export const post = (path, body) => api("POST", path, body === undefined ? {} : body);
/** A file's bytes as the request body (e.g. a class-list YAML to POST /class-lists). */
export const postFile = (path, file, contentType) => api("POST", path, file, contentType);
export const patch = (path, body) => api("PATCH", path, body);
export const put = (path, body) => api("PUT", path, body);
export const del = (path) => api("DELETE", path);

/** Class names go into URL paths. */
export const enc = encodeURIComponent;
