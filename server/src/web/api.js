// The REST API with the pasted token. The token lives in this tab's sessionStorage only and
// travels in the Authorization header, never in a URL.

const KEY = "helmholtz.token";

export function token() {
  return sessionStorage.getItem(KEY);
}

export function setToken(t) {
  if (t) sessionStorage.setItem(KEY, t.trim());
  else sessionStorage.removeItem(KEY);
}

export class ApiError extends Error {
  constructor(status, problem) {
    super(problem?.detail || problem?.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
  }
}

function headers(extra = {}) {
  const h = { ...extra };
  const t = token();
  if (t) h.Authorization = `Bearer ${t}`;
  return h;
}

async function failure(r) {
  let problem = null;
  try {
    problem = await r.json();
  } catch (_) {
    /* not JSON */
  }
  return new ApiError(r.status, problem);
}

/** A raw response (throws ApiError unless 2xx). */
export async function request(path, { method = "GET", body, type, signal } = {}) {
  const extra = type ? { "Content-Type": type } : {};
  const r = await fetch(path, { method, body, headers: headers(extra), signal, cache: "no-store" });
  if (!r.ok) throw await failure(r);
  return r;
}

export async function json(path, opts = {}) {
  return (await request(path, opts)).json();
}

export async function postJson(path, value) {
  return json(path, { method: "POST", body: JSON.stringify(value), type: "application/json" });
}

export async function bytes(path, opts = {}) {
  return new Uint8Array(await (await request(path, opts)).arrayBuffer());
}

/**
 * Server-sent events over fetch (EventSource cannot send the Authorization header): calls
 * onEvent(name, data) per event until the stream ends or `signal` aborts.
 */
export async function events(path, onEvent, signal) {
  const r = await request(path, { signal });
  const reader = r.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += decoder.decode(value, { stream: true });
    let cut;
    while ((cut = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, cut);
      buffer = buffer.slice(cut + 2);
      let name = "message";
      const data = [];
      for (const line of block.split("\n")) {
        if (line.startsWith(":")) continue;
        if (line.startsWith("event:")) name = line.slice(6).trim();
        else if (line.startsWith("data:")) data.push(line.slice(5).replace(/^ /, ""));
      }
      if (data.length) onEvent(name, JSON.parse(data.join("\n")));
    }
  }
}

/** Saves a file fetched with the token (downloads cannot carry headers themselves). */
export async function download(path, filename) {
  const blob = await (await request(path)).blob();
  const url = URL.createObjectURL(blob);
  const a = document.createElement("a");
  a.href = url;
  a.download = filename;
  document.body.append(a);
  a.click();
  a.remove();
  setTimeout(() => URL.revokeObjectURL(url), 10000);
}

/** An object URL of an image fetched with the token. */
export async function imageUrl(path) {
  const blob = await (await request(path)).blob();
  return URL.createObjectURL(blob);
}
