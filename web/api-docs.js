// The REST reference at /api/docs: renders /api/v1/openapi.json with no third-party code, so it works
// offline. Text from the spec is always set as textContent, never parsed as HTML.

const SPEC = "/api/v1/openapi.json";
const METHODS = ["get", "post", "put", "patch", "delete"];

function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs)) {
    if (k === "class") node.className = v;
    else node.setAttribute(k, v);
  }
  for (const c of children.flat()) {
    if (c === null || c === undefined || c === "") continue;
    node.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return node;
}

/** A short type name for a JSON schema: "ProjectPublic", "integer", "array of RunPublic", "string | null". */
function typeName(schema) {
  if (!schema) return "";
  if (schema.$ref) return schema.$ref.split("/").pop();
  if (schema.anyOf) return schema.anyOf.map(typeName).join(" | ");
  if (schema.oneOf) return schema.oneOf.map(typeName).join(" | ");
  if (schema.allOf) return schema.allOf.map(typeName).join(" & ");
  if (schema.enum) return schema.enum.map((v) => JSON.stringify(v)).join(" | ");
  if (schema.const !== undefined) return JSON.stringify(schema.const);
  if (schema.type === "array") return `array of ${typeName(schema.items) || "any"}`;
  if (schema.type === "object" && schema.additionalProperties) return `object of ${typeName(schema.additionalProperties)}`;
  return schema.type || "any";
}

function schemaLink(schema) {
  const name = typeName(schema);
  return schema && schema.$ref ? el("a", { href: `#schema-${name}` }, name) : el("code", {}, name);
}

function parametersTable(params) {
  if (!params || !params.length) return null;
  return el(
    "table",
    {},
    el("tr", {}, el("th", {}, "parameter"), el("th", {}, "in"), el("th", {}, "type"), el("th", {}, "description")),
    params.map((p) =>
      el(
        "tr",
        {},
        el("td", {}, el("code", {}, p.name), p.required ? el("span", { class: "req" }, " *") : null),
        el("td", {}, p.in),
        el("td", {}, schemaLink(p.schema)),
        el("td", {}, p.description || (p.schema && p.schema.description) || ""),
      ),
    ),
  );
}

function bodySection(body) {
  if (!body || !body.content) return null;
  const [type, media] = Object.entries(body.content)[0];
  return el("p", {}, el("strong", {}, "Body "), el("span", { class: "muted" }, `(${type}) `), schemaLink(media.schema));
}

function responsesTable(responses) {
  return el(
    "table",
    {},
    el("tr", {}, el("th", {}, "status"), el("th", {}, "description"), el("th", {}, "content")),
    Object.entries(responses || {}).map(([code, r]) => {
      const media = r.content ? Object.values(r.content)[0] : null;
      return el("tr", {}, el("td", {}, code), el("td", {}, r.description || ""), el("td", {}, media ? schemaLink(media.schema) : ""));
    }),
  );
}

function operation(path, method, op) {
  const text = `${method} ${path} ${(op.tags || []).join(" ")} ${op.summary || ""}`.toLowerCase();
  return el(
    "details",
    { class: "op", "data-search": text, id: op.operationId || `${method}-${path}` },
    el("summary", {}, el("span", { class: `method ${method}` }, method), el("code", {}, path), el("span", { class: "muted" }, op.summary || "")),
    el(
      "div",
      { class: "op-body" },
      op.description ? el("pre", {}, op.description) : null,
      parametersTable(op.parameters),
      bodySection(op.requestBody),
      responsesTable(op.responses),
    ),
  );
}

function schemaBlock(name, schema) {
  const required = new Set(schema.required || []);
  const props = Object.entries(schema.properties || {});
  return el(
    "div",
    { id: `schema-${name}` },
    el("h3", {}, name),
    schema.description ? el("p", { class: "muted" }, schema.description) : null,
    props.length
      ? el(
          "table",
          {},
          el("tr", {}, el("th", {}, "field"), el("th", {}, "type"), el("th", {}, "description")),
          props.map(([field, s]) =>
            el(
              "tr",
              {},
              el("td", {}, el("code", {}, field), required.has(field) ? el("span", { class: "req" }, " *") : null),
              el("td", {}, schemaLink(s)),
              el("td", {}, s.description || ""),
            ),
          ),
        )
      : el("p", {}, el("code", {}, typeName(schema))),
  );
}

async function main() {
  const ops = document.getElementById("ops");
  let spec;
  try {
    const response = await fetch(SPEC, { headers: { Accept: "application/json" } });
    if (!response.ok) throw new Error(`HTTP ${response.status}`);
    spec = await response.json();
  } catch (err) {
    ops.replaceChildren(el("p", { class: "req" }, `Could not load ${SPEC}: ${err.message}`));
    return;
  }
  document.getElementById("title").textContent = `${spec.info.title} API ${spec.info.version}`;
  document.getElementById("summary").textContent = spec.info.summary || spec.info.description || "";

  const byTag = new Map();
  for (const [path, item] of Object.entries(spec.paths || {})) {
    for (const method of METHODS) {
      if (!item[method]) continue;
      const tag = (item[method].tags || ["other"])[0];
      if (!byTag.has(tag)) byTag.set(tag, []);
      byTag.get(tag).push(operation(path, method, item[method]));
    }
  }
  const sections = [...byTag.entries()].map(([tag, items]) => el("section", { id: `tag-${tag}` }, el("h2", {}, tag), items));
  ops.replaceChildren(...sections);
  document.getElementById("toc").replaceChildren(...[...byTag.keys()].map((tag) => el("a", { href: `#tag-${tag}` }, tag)));
  const schemas = (spec.components && spec.components.schemas) || {};
  document.getElementById("schemas").replaceChildren(...Object.entries(schemas).map(([name, s]) => schemaBlock(name, s)));

  document.getElementById("filter").addEventListener("input", (e) => {
    const q = e.target.value.trim().toLowerCase();
    for (const section of sections) {
      let shown = 0;
      for (const op of section.querySelectorAll("details.op")) {
        const match = !q || op.dataset.search.includes(q);
        op.hidden = !match;
        shown += match ? 1 : 0;
      }
      section.hidden = shown === 0;
    }
  });
}

main();
