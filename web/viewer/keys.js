// Keyboard shortcuts of the 3D viewer, and the "?" overlay that lists them.
//
// viser's client has no keyboard API, so shortcuts live here, in the page the app relays (see overlay.js).
// Each feature module binds its keys with `bind`; the "?" overlay is built from the same table, so it lists
// exactly the keys that work.

const bindings = [];

/** A printable name for a key combination like "ctrl+shift+z" or "ArrowRight". */
function keyLabel(combo) {
  const names = { arrowleft: "←", arrowright: "→", arrowup: "↑", arrowdown: "↓", " ": "Space", escape: "Esc" };
  return combo
    .split("+")
    .map((part) => names[part.toLowerCase()] || (part.length === 1 ? part.toUpperCase() : part[0].toUpperCase() + part.slice(1)))
    .join("+");
}

/** The normalised combination of a keydown event: modifiers in a fixed order, then the key, lower case. */
export function comboOf(event) {
  const parts = [];
  if (event.ctrlKey || event.metaKey) parts.push("ctrl");
  if (event.altKey) parts.push("alt");
  // Shift is part of the character for "?" and digits on some layouts; keep it only for letters/arrows.
  const key = event.key.length === 1 ? event.key.toLowerCase() : event.key.toLowerCase();
  if (event.shiftKey && (key.length > 1 || /[a-z]/.test(key))) parts.push("shift");
  parts.push(key);
  return parts.join("+");
}

/**
 * Bind `combos` (e.g. ["arrowright", "."]) to `handler(event)`. `group` and `what` describe it in the
 * "?" overlay, which shows `shown` (e.g. ["1-9"]) instead of the combinations when given. Bindings live as
 * long as the page.
 */
export function bind(combos, what, handler, group = "General", shown = null) {
  bindings.push({ combos: combos.map((c) => c.toLowerCase()), what, handler, group, shown });
}

/** True when the key went to a text field (viser's own inputs): shortcuts must not steal typing. */
function typing(event) {
  const el = event.target;
  if (!el || !el.tagName) return false;
  const tag = el.tagName.toLowerCase();
  // viser's dropdowns keep focus in their <input> after a pick (read-only in some versions, a closed
  // combobox in others): that is not typing. An open one takes the keys (its list is being browsed).
  if (tag === "input" && el.readOnly) return false;
  if (tag === "input" && el.getAttribute("role") === "combobox" && el.getAttribute("aria-expanded") !== "true") {
    return false;
  }
  return tag === "input" || tag === "textarea" || tag === "select" || el.isContentEditable;
}

let help = null;

function toggleHelp() {
  if (help) {
    help.remove();
    help = null;
    return;
  }
  help = document.createElement("div");
  help.id = "leap-shortcuts";
  help.setAttribute("role", "dialog");
  help.setAttribute("aria-label", "Keyboard shortcuts");
  const groups = new Map();
  for (const b of bindings) {
    if (!groups.has(b.group)) groups.set(b.group, []);
    groups.get(b.group).push(b);
  }
  const title = document.createElement("h2");
  title.textContent = "Keyboard shortcuts";
  help.append(title);
  for (const [group, items] of groups) {
    const h = document.createElement("h3");
    h.textContent = group;
    const table = document.createElement("table");
    for (const b of items) {
      const row = table.insertRow();
      const keys = row.insertCell();
      keys.className = "keys";
      for (const c of b.shown || b.combos) {
        const k = document.createElement("kbd");
        k.textContent = b.shown ? c : keyLabel(c);
        keys.append(k, " ");
      }
      row.insertCell().textContent = b.what;
    }
    help.append(h, table);
  }
  const close = document.createElement("p");
  close.className = "hint";
  close.textContent = "Press ? or Esc to close.";
  help.append(close);
  document.body.append(help);
}

/** Start listening (called once by overlay.js after every module has bound its keys). */
export function listen() {
  bind(["?"], "Show or hide this list", toggleHelp);
  window.addEventListener(
    "keydown",
    (event) => {
      if (typing(event)) return;
      const combo = comboOf(event);
      if (help && combo === "escape") {
        toggleHelp();
        event.preventDefault();
        return;
      }
      // Several modules may bind one key (Esc puts the selection tool down and leaves the review): all run.
      const matched = bindings.filter((x) => x.combos.includes(combo));
      if (!matched.length) return;
      event.preventDefault();
      event.stopPropagation();
      for (const b of matched) {
        Promise.resolve()
          .then(() => b.handler(event))
          .catch((err) => notify(err.message || String(err), "error"));
      }
    },
    true,
  );
}

let toastTimer = null;

/** A short message at the bottom of the viewer (errors of shortcut actions, confirmations). */
export function notify(text, kind = "info") {
  let el = document.getElementById("leap-toast");
  if (!el) {
    el = document.createElement("div");
    el.id = "leap-toast";
    el.setAttribute("role", "status");
    document.body.append(el);
  }
  el.textContent = text;
  el.dataset.kind = kind;
  el.hidden = false;
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => (el.hidden = true), kind === "error" ? 6000 : 2500);
}
