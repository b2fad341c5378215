// Reconstruction jobs: a form generated from the OpenAPI document the server serves (the
// methods are the enum of ReconstructionRequest.method, which the server derives from its own
// parser), live progress from the server-sent events of GET /v1/reconstructions/{id}/events
// (read with fetch so the token stays in a header), and cancellation.

import { json, postJson, events } from "./api.js";
import { h, say } from "./dom.js";

let documentCache = null;
async function openapi() {
  if (!documentCache) documentCache = await (await fetch("/openapi.json")).json();
  return documentCache;
}

function watch(rec, list, onFinished) {
  const bar = h("progress", { max: 1, value: rec.progress || 0, "aria-label": `reconstruction ${rec.id} progress` });
  const badge = h("span", { class: `badge ${rec.state}`, "data-state": rec.state }, rec.state);
  const pct = h("span", {}, `${Math.round(100 * (rec.progress || 0))} %`);
  const controller = new AbortController();
  const cancel = h("button", { type: "button", class: "cancel", onclick: async () => {
    cancel.disabled = true;
    try {
      await postJson(`/v1/reconstructions/${rec.id}/cancel`, {});
      say(`Reconstruction ${rec.id} cancelled`);
    } catch (e) {
      say(`Cancel: ${e.message}`, "error");
      cancel.disabled = false;
    }
  } }, "Cancel");
  const row = h("li", { "data-job": rec.id }, h("strong", {}, `#${rec.id} ${rec.method}`), " ", badge, " ", bar, " ", pct, " ", cancel);
  list.prepend(row);
  const update = (r) => {
    badge.textContent = r.state;
    badge.className = `badge ${r.state}`;
    badge.dataset.state = r.state;
    bar.value = r.progress || 0;
    pct.textContent = `${Math.round(100 * (r.progress || 0))} %${r.error ? ` — ${r.error}` : ""}`;
    const ended = ["done", "failed", "cancelled"].includes(r.state);
    cancel.hidden = ended;
    row.dataset.events = String((Number(row.dataset.events) || 0) + 1);
    if (ended && (r.warnings || []).length && !row.querySelector(".warnings")) {
      row.append(h("ul", { class: "warnings", role: "status" }, ...r.warnings.map((w) => h("li", {}, `warning: ${w}`))));
    }
    if (ended) {
      say(`Reconstruction ${r.id} ${r.state}`);
      if (r.state === "done") onFinished?.(r);
    }
  };
  events(`/v1/reconstructions/${rec.id}/events`, (name, data) => name === "reconstruction" && update(data), controller.signal)
    .catch((e) => e.name !== "AbortError" && say(`Progress of ${rec.id}: ${e.message}`, "error"));
  return controller;
}

export async function jobsPanel(session, signal) {
  const doc = await openapi();
  const schema = doc.components.schemas.ReconstructionRequest;
  const methods = (schema.properties.method.enum || []).filter((m) => (session.camera ? m === "transport" : m !== "transport"));
  const method = h("select", { id: "job-method", name: "method" }, methods.map((m) => h("option", { value: m }, m)));
  const params = h("textarea", { id: "job-params", name: "params", rows: 3, spellcheck: "false" }, "{}");
  const list = h("ul", { id: "jobs", class: "jobs" });
  const error = h("p", { class: "error", role: "alert", id: "job-error" });
  const form = h("form", { id: "job-form" },
    h("label", { for: "job-method" }, "Method"), method,
    h("label", { for: "job-params" }, "Parameters (JSON object; ", h("a", { href: "/docs" }, "the methods' parameters"), ")"), params,
    h("button", { type: "submit", id: "job-submit" }, "Reconstruct"));
  const reload = () => {
    // The new reconstruction joins the tables, images and relighting.
    window.dispatchEvent(new HashChangeEvent("hashchange"));
  };
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    error.textContent = "";
    let p;
    try {
      p = JSON.parse(params.value || "{}");
    } catch (err) {
      error.textContent = `Parameters: not JSON (${err.message})`;
      return;
    }
    try {
      const rec = await postJson(`/v1/sessions/${encodeURIComponent(session.id)}/reconstructions`, { method: method.value, params: p });
      say(`Reconstruction ${rec.id} queued`);
      const c = watch(rec, list, null);
      signal.addEventListener("abort", () => c.abort());
    } catch (err) {
      error.textContent = err.problem?.field ? `${err.problem.field}: ${err.message}` : err.message;
    }
  });
  // Jobs of this session that are still queued or running.
  const { reconstructions } = await json(`/v1/sessions/${encodeURIComponent(session.id)}/reconstructions`, { signal });
  for (const r of reconstructions.filter((r) => r.state === "queued" || r.state === "running")) {
    const c = watch(r, list, null);
    signal.addEventListener("abort", () => c.abort());
  }
  return h("section", { class: "card", id: "jobs-panel", "aria-labelledby": "jobs-h" },
    h("h2", { id: "jobs-h" }, "Request a reconstruction"),
    h("p", { class: "help" }, schema.description || ""),
    form, error,
    h("button", { type: "button", id: "jobs-reload", onclick: reload }, "Reload the page's reconstructions"),
    list);
}
