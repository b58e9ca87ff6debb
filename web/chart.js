// Per-class IoU of several runs side by side: horizontal grouped bars drawn as SVG.

import { s } from "./dom.js";

export const RUN_COLORS = ["#3b6fe0", "#f08c2e", "#22a06b", "#d6453d", "#8a5cd6", "#1a9bb8"];

/**
 * @param {Array<{label: string, iou: Object<string, number|null>}>} series  one entry per run
 * @param {Array<{name: string, color: string}>} classes  rows, in schema order
 */
export function iouChart(series, classes) {
  const labelW = 128;
  const barArea = 420;
  const valueW = 44;
  const barH = 9;
  const gap = 2;
  const groupPad = 8;
  const top = 22;
  const groupH = series.length * (barH + gap) - gap;
  const height = top + classes.length * (groupH + groupPad) + 6;
  const width = labelW + barArea + valueW;

  const root = s("svg", {
    class: "iou-chart",
    viewBox: `0 0 ${width} ${height}`,
    width: "100%",
    role: "img",
    "aria-label": "Per-class IoU of the selected runs",
  });
  // Grid lines every 20 %.
  for (let p = 0; p <= 100; p += 20) {
    const x = labelW + (barArea * p) / 100;
    root.append(s("line", { x1: x, x2: x, y1: top - 4, y2: height - 4, class: "grid" }));
    root.append(s("text", { x, y: 12, class: "axis", "text-anchor": "middle" }, `${p}`));
  }
  classes.forEach((cls, ci) => {
    const y0 = top + ci * (groupH + groupPad);
    const g = s("g", { class: "group" });
    g.append(s("rect", { x: 2, y: y0 + groupH / 2 - 5, width: 10, height: 10, rx: 2, fill: cls.color, class: "swatch" }));
    const shown = cls.name.length > 17 ? cls.name.slice(0, 16) + "…" : cls.name;
    g.append(s("text", { x: 17, y: y0 + groupH / 2 + 4, class: "label" }, shown, s("title", {}, cls.name)));
    series.forEach((run, ri) => {
      const v = run.iou[cls.name];
      const y = y0 + ri * (barH + gap);
      const w = v === null || v === undefined ? 0 : Math.max(0.5, barArea * v);
      const color = RUN_COLORS[ri % RUN_COLORS.length];
      const bar = s("rect", { x: labelW, y, width: w, height: barH, rx: 1.5, fill: color });
      bar.append(s("title", {}, `${run.label} · ${cls.name}: ${v === null || v === undefined ? "absent" : (100 * v).toFixed(1) + " %"}`));
      g.append(bar);
      g.append(
        s(
          "text",
          { x: labelW + w + 4, y: y + barH - 1, class: "value" },
          v === null || v === undefined ? "–" : (100 * v).toFixed(1),
        ),
      );
    });
    root.append(g);
  });
  return root;
}
