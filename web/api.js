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

/** A 422 location as a field path: ["body", "classes", 19, "name"] → "classes[19].name". */
export function fieldPath(loc) {
  let path = "";
  for (const [i, part] of (loc || []).entries()) {
    if (i === 0 && ["body", "query", "path"].includes(part)) continue; // where FastAPI found the field
    if (typeof part === "number" || /^\d+$/.test(String(part))) path += `[${part}]`;
    else path += path ? `.${part}` : String(part);
  }
  return path;
}

/** What a validation error says of its field, in words (pydantic's error types), without the field. */
function problemText(d) {
  const c = d.ctx || {};
  // The server sends the context's values as text ("1"): numbers come back as numbers.
  const n = (k) => (c[k] !== undefined && c[k] !== null && !Number.isNaN(Number(c[k])) ? Number(c[k]) : c[k]);
  switch (d.type) {
    case "missing":
      return "is required";
    case "string_too_short":
      return n("min_length") === 1 ? "must not be empty" : `must have at least ${n("min_length")} characters`;
    case "string_too_long":
      return `must have at most ${n("max_length")} characters`;
    case "too_short":
      return `must list at least ${n("min_length")} item${n("min_length") === 1 ? "" : "s"}`;
    case "too_long":
      return `must list at most ${n("max_length")} items`;
    case "greater_than_equal":
      return `must be at least ${n("ge")}`;
    case "greater_than":
      return `must be more than ${n("gt")}`;
    case "less_than_equal":
      return `must be at most ${n("le")}`;
    case "less_than":
      return `must be less than ${n("lt")}`;
    case "int_parsing":
    case "int_type":
      return "must be a whole number";
    case "float_parsing":
    case "float_type":
      return "must be a number";
    case "bool_parsing":
    case "bool_type":
      return "must be true or false";
    case "extra_forbidden":
      return "is not a known field";
    case "literal_error":
      return `must be ${n("expected")}`;
    default: {
      const msg = String(d.msg || "").replace(/^(Value error|Assertion failed), /, "");
      return msg ? msg[0].toLowerCase() + msg.slice(1) : "is not valid";
    }
  }
}

/** One field-named sentence per validation error ("name: must not be empty"); a message that names its
 * field already ("classes[19].name: ...", an uploaded file's "classes[3].prompts: ...") is kept as it is. */
function validationText(d) {
  const path = fieldPath(d.loc);
  let msg = problemText(d);
  // A message may start by naming its field ("classes: classes[19] ...", "classes[19].name: ..."): keep its
  // own, more precise naming and drop the repeated prefix.
  const root = path.split(/[.[]/)[0];
  const names = (text) => root && text.startsWith(root) && /^[.:[]/.test(text.slice(root.length));
  while (msg.startsWith(`${root}: `) && names(msg.slice(root.length + 2))) msg = msg.slice(root.length + 2);
  if (!path || names(msg)) return msg;
  return `${path}: ${msg}`;
}

export function errorText(detail) {
  if (detail === null || detail === undefined) return "";
  if (typeof detail === "string") return detail;
  if (Array.isArray(detail)) return detail.map(validationText).join("; ");
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
