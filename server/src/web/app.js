// The viewer: a token pasted once (or given as /#token=... by the demo's link; a URL fragment
// never reaches the server), then the lab's sessions and each session's page.

import { token, setToken, json, ApiError } from "./api.js";
import { h, say } from "./dom.js";
import { sessionPage } from "./session.js";

// State for tests and the curious: what the viewer did (see docs/web-viewer.md).
window.hz = window.hz || {};

function takeTokenFromFragment() {
  const m = /^#token=([^&]+)/.exec(location.hash);
  if (m) {
    setToken(decodeURIComponent(m[1]));
    // Out of the address bar and history at once.
    history.replaceState(null, "", "/#/");
  }
}

const main = () => document.getElementById("main");
let pageTimer = null;
let pageAbort = null;

function clearPage() {
  if (pageTimer) clearInterval(pageTimer);
  pageTimer = null;
  if (pageAbort) pageAbort.abort();
  pageAbort = new AbortController();
  main().replaceChildren();
  return pageAbort.signal;
}

function loginPage(message) {
  clearPage();
  document.getElementById("logout").hidden = true;
  document.getElementById("who").textContent = "";
  const input = h("input", { id: "token", type: "password", autocomplete: "off", required: true, placeholder: "hz_…", "aria-describedby": "token-help" });
  const form = h("form", { id: "login", class: "card narrow" },
    h("h1", {}, "Open the viewer"),
    h("label", { for: "token" }, "Token of your lab (reader role)"),
    input,
    h("p", { id: "token-help", class: "help" }, "Kept in this browser tab only (session storage) and sent as an Authorization header; never put in a URL. ",
      "Make one with ", h("code", {}, "helmholtz-server token create --lab LAB --role reader"), "."),
    message ? h("p", { class: "error", role: "alert" }, message) : null,
    h("button", { type: "submit" }, "Open"));
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    setToken(input.value);
    await route();
  });
  main().append(form);
  input.focus();
}

function stateBadge(state) {
  return h("span", { class: `badge ${state}` }, state);
}

function kind(s) {
  if (s.camera) return `camera ${s.camera.width}×${s.camera.height} (${s.camera.format})`;
  return `${s.channels.length} detector${s.channels.length === 1 ? "" : "s"} (${s.channels.join(", ")})`;
}

function progress(s) {
  const pct = s.expected_rows ? Math.min(100, (100 * s.committed_rows) / s.expected_rows) : 0;
  return h("div", { class: "rows" },
    h("progress", { max: s.expected_rows || 1, value: s.committed_rows, "aria-label": `${s.id}: ${s.committed_rows} of ${s.expected_rows} rows` }),
    h("span", {}, `${s.committed_rows.toLocaleString()} / ${s.expected_rows.toLocaleString()} (${pct.toFixed(0)} %)`));
}

async function sessionsPage() {
  const signal = clearPage();
  const table = h("table", { id: "sessions" },
    h("caption", {}, "Sessions of your lab, newest first (updated every 2 s)"),
    h("thead", {}, h("tr", {}, ["Session", "Rig", "Patterns", "Detectors / camera", "State", "Rows committed / expected", "Latest reconstruction"].map((t) => h("th", { scope: "col" }, t)))),
    h("tbody"));
  main().append(h("h1", {}, "Sessions"), table);
  const fill = async () => {
    const list = await json("/v1/sessions", { signal });
    const rows = list.sessions.map((s) => h("tr", { "data-session": s.id },
      h("th", { scope: "row" }, h("a", { href: `#/sessions/${encodeURIComponent(s.id)}` }, s.id)),
      h("td", {}, s.rig),
      h("td", {}, `${s.patterns.family} ${s.patterns.width}×${s.patterns.height}, ${s.patterns.count.toLocaleString()}`),
      h("td", {}, kind(s)),
      h("td", {}, stateBadge(s.state)),
      h("td", {}, progress(s)),
      h("td", {}, s.latest_reconstruction ?? "—")));
    table.tBodies[0].replaceChildren(...rows);
    if (!rows.length) table.tBodies[0].append(h("tr", {}, h("td", { colspan: 7 }, "No sessions yet.")));
    window.hz.sessions = list.sessions.map((s) => s.id);
  };
  await fill();
  pageTimer = setInterval(() => fill().catch((e) => say(`Could not refresh: ${e.message}`, "error")), 2000);
}

export async function route() {
  takeTokenFromFragment();
  if (!token()) return loginPage();
  document.getElementById("logout").hidden = false;
  const path = location.hash.replace(/^#/, "") || "/";
  try {
    const m = /^\/sessions\/([^/?]+)/.exec(path);
    if (m) {
      const signal = clearPage();
      await sessionPage(main(), decodeURIComponent(m[1]), signal, (t) => (pageTimer = t));
    } else {
      await sessionsPage();
    }
    document.getElementById("who").textContent = "token set";
  } catch (e) {
    if (e instanceof ApiError && e.status === 401) {
      setToken(null);
      return loginPage("That token was not accepted (unknown or revoked). Paste another.");
    }
    if (e.name === "AbortError") return;
    main().append(h("p", { class: "error", role: "alert", id: "page-error" }, e.message));
    say(e.message, "error");
  }
}

document.getElementById("logout").addEventListener("click", () => {
  setToken(null);
  location.hash = "#/";
  loginPage();
});
window.addEventListener("hashchange", route);
route();
