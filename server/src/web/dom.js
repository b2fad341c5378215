// Small DOM helpers.

/** An element: h("p", {class: "x"}, "text", child, ...). */
export function h(tag, attrs = {}, ...children) {
  const el = document.createElement(tag);
  for (const [k, v] of Object.entries(attrs || {})) {
    if (v === undefined || v === null || v === false) continue;
    if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
    else if (k === "class") el.className = v;
    else if (k === "text") el.textContent = v;
    else el.setAttribute(k, v === true ? "" : v);
  }
  for (const c of children.flat()) {
    if (c === undefined || c === null || c === false) continue;
    el.append(c instanceof Node ? c : document.createTextNode(String(c)));
  }
  return el;
}

/** Announces `text` in the live region (screen readers read it). */
export function say(text, kind = "info") {
  const s = document.getElementById("status");
  s.textContent = text;
  s.dataset.kind = kind;
}

export function fmt(v, digits = 3) {
  if (v === null || v === undefined) return "—";
  if (v === "inf") return "∞";
  if (typeof v !== "number") return String(v);
  if (!Number.isFinite(v)) return "—";
  if (Math.abs(v) >= 1000 || (Math.abs(v) < 1e-3 && v !== 0)) return v.toExponential(2);
  return Number(v.toPrecision(digits)).toString();
}
