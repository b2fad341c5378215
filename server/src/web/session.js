// A session's page: its declaration, its reconstructions with their reports, the speed against
// the error of all of them, the dual images (per channel, colour composite, side by side), the
// live preview while it uploads, relighting, the primal prediction, photometric normals and
// albedo, and reconstruction jobs.

import { json, bytes, download, events } from "./api.js";
import { h, say, fmt } from "./dom.js";
import { parseNpy } from "./npy.js";
import { ImageView } from "./image.js";
import { relightPanel, primalPanel, photometricPanel } from "./relight.js";
import { jobsPanel } from "./jobs.js";

/** What a report says, as table cells: chosen model and weight, held-out error, PSNR/SSIM. */
export function summary(r) {
  const rep = r.report || {};
  const auto = rep.details?.auto?.[0];
  const model = auto ? `${auto.model}${auto.lambda_fraction != null ? ` (λ/λmax ${fmt(auto.lambda_fraction)})` : auto.lambda != null ? ` (λ ${fmt(auto.lambda)})` : ""}` : rep.details?.transform ? `${rep.details.transform}${rep.details.lambda != null ? ` (λ ${fmt(rep.details.lambda)})` : ""}` : "—";
  const heldOut = rep.held_out?.relative_residual ?? null;
  let psnr = null;
  let ssim = null;
  let truthError = null;
  if (Array.isArray(rep.quality) && rep.quality.length) {
    psnr = rep.quality[0].psnr_db;
    ssim = rep.quality[0].ssim;
    truthError = rep.quality[0].relative_error;
  } else if (rep.quality && typeof rep.quality === "object") {
    psnr = rep.quality.camera_dual_psnr_db ?? null;
    ssim = rep.quality.camera_dual_ssim ?? null;
    truthError = rep.quality.transport_relative_error ?? null;
  }
  return { model, heldOut, psnr, ssim, truthError, seconds: r.seconds ?? rep.seconds ?? null };
}

function detailsCard(s) {
  const items = [
    ["Rig", s.rig],
    ["State", s.state],
    ["Rows", `${s.committed_rows.toLocaleString()} committed of ${s.expected_rows.toLocaleString()} expected`],
    ["Ground truth", s.has_ground_truth ? "known (PSNR and SSIM are reported)" : "not known"],
    ["Created", new Date(s.created_unix_ms).toISOString()],
  ];
  const sensors = s.camera
    ? h("p", { id: "camera" }, `Camera ${s.camera.width}×${s.camera.height}, ${s.camera.format} frames`)
    : h("table", { id: "detectors" }, h("caption", {}, "Detectors"),
      h("thead", {}, h("tr", {}, h("th", { scope: "col" }, "Channel"), h("th", { scope: "col" }, "Direction (x, y, z)"))),
      h("tbody", {}, s.channels.map((c, i) => h("tr", {}, h("td", {}, c), h("td", {}, s.directions[i] ? s.directions[i].map((v) => fmt(v)).join(", ") : "—")))));
  return h("section", { class: "card", "aria-labelledby": "decl" },
    h("h2", { id: "decl" }, "Declaration"),
    h("dl", {}, items.flatMap(([k, v]) => [h("dt", {}, k), h("dd", {}, v)])),
    h("h3", {}, "Pattern spec"),
    h("pre", { id: "spec" }, JSON.stringify(s.patterns, null, 2)),
    sensors);
}

function reconTable(recons) {
  return h("table", { id: "reconstructions" },
    h("caption", {}, "Reconstructions"),
    h("thead", {}, h("tr", {}, ["Id", "Method", "State", "Rows", "Chosen model (weight)", "Held-out error", "Seconds", "PSNR dB", "SSIM"].map((t) => h("th", { scope: "col" }, t)))),
    h("tbody", {}, recons.map((r) => {
      const m = summary(r);
      return h("tr", { "data-reconstruction": r.id },
        h("td", {}, r.id), h("td", {}, r.method), h("td", {}, h("span", { class: `badge ${r.state}` }, r.state)), h("td", {}, r.rows.toLocaleString()),
        h("td", {}, m.model), h("td", {}, fmt(m.heldOut)), h("td", {}, fmt(m.seconds)), h("td", {}, fmt(m.psnr)), h("td", {}, fmt(m.ssim)));
    })));
}

/** Seconds (log) against error (log) of every finished reconstruction, as SVG. */
export function plot(recons) {
  const W = 520;
  const H = 300;
  const L = 64;
  const B = 44;
  const pts = [];
  for (const r of recons) {
    if (r.state !== "done") continue;
    const m = summary(r);
    if (m.seconds > 0 && m.heldOut > 0) pts.push({ r, x: m.seconds, y: m.heldOut, kind: "held-out" });
    if (m.seconds > 0 && m.truthError > 0) pts.push({ r, x: m.seconds, y: m.truthError, kind: "truth" });
  }
  const svgNs = "http://www.w3.org/2000/svg";
  const s = (tag, attrs = {}, text) => {
    const el = document.createElementNS(svgNs, tag);
    for (const [k, v] of Object.entries(attrs)) el.setAttribute(k, v);
    if (text !== undefined) el.textContent = text;
    return el;
  };
  const svg = s("svg", { viewBox: `0 0 ${W} ${H}`, role: "img", id: "speed-error", class: "plot" });
  const without = recons.filter((r) => r.state === "done" && !(summary(r).heldOut > 0)).map((r) => `${r.id} (${r.method})`);
  svg.append(s("title", {}, `Speed against error of ${new Set(pts.map((p) => p.r.id)).size} finished reconstructions`));
  if (!pts.length) {
    svg.append(s("text", { x: W / 2, y: H / 2, "text-anchor": "middle" }, "No finished reconstruction with an error estimate yet"));
    return h("figure", { class: "card" }, svg, without.length ? h("figcaption", {}, `Without a held-out error: ${without.join(", ")}`) : null);
  }
  const lx = pts.map((p) => Math.log10(p.x));
  const ly = pts.map((p) => Math.log10(p.y));
  const pad = (a, b) => (b - a < 0.2 ? [a - 0.1, b + 0.1] : [a - 0.05 * (b - a), b + 0.05 * (b - a)]);
  const [x0, x1] = pad(Math.min(...lx), Math.max(...lx));
  const [y0, y1] = pad(Math.min(...ly), Math.max(...ly));
  const X = (v) => L + ((Math.log10(v) - x0) / (x1 - x0)) * (W - L - 16);
  const Y = (v) => H - B - ((Math.log10(v) - y0) / (y1 - y0)) * (H - B - 12);
  svg.append(s("line", { x1: L, y1: H - B, x2: W - 8, y2: H - B, class: "axis" }), s("line", { x1: L, y1: 8, x2: L, y2: H - B, class: "axis" }));
  for (const [v, axis] of [[10 ** x0, "x"], [10 ** x1, "x"], [10 ** y0, "y"], [10 ** y1, "y"]]) {
    if (axis === "x") svg.append(s("text", { x: X(v), y: H - B + 16, "text-anchor": "middle", class: "tick" }, fmt(v, 2)));
    else svg.append(s("text", { x: L - 6, y: Y(v) + 4, "text-anchor": "end", class: "tick" }, fmt(v, 2)));
  }
  svg.append(s("text", { x: (L + W) / 2, y: H - 6, "text-anchor": "middle" }, "seconds (log)"));
  svg.append(s("text", { x: 14, y: (H - B) / 2, transform: `rotate(-90 14 ${(H - B) / 2})`, "text-anchor": "middle" }, "relative error (log)"));
  for (const p of pts) {
    const g = s("g", { class: `point ${p.kind}`, "data-reconstruction": p.r.id });
    const shape = p.kind === "truth"
      ? s("rect", { x: X(p.x) - 4, y: Y(p.y) - 4, width: 8, height: 8 })
      : s("circle", { cx: X(p.x), cy: Y(p.y), r: 5 });
    g.append(shape, s("title", {}, `#${p.r.id} ${p.r.method}: ${fmt(p.x)} s, ${p.kind} error ${fmt(p.y)}`));
    g.append(s("text", { x: X(p.x) + 7, y: Y(p.y) - 6, class: "tick" }, `${p.r.method} #${p.r.id}`));
    svg.append(g);
  }
  return h("figure", { class: "card" }, svg,
    h("figcaption", {}, "Speed against error: ● held-out error (no truth needed), ■ error against the ground truth. ",
      without.length ? `Without a held-out error: ${without.join(", ")}.` : ""));
}

/** The dual images of the done reconstructions, a second one side by side, and downloads. */
function imagesPanel(session, recons) {
  const done = recons.filter((r) => r.state === "done");
  const section = h("section", { class: "card", "aria-labelledby": "images-h" }, h("h2", { id: "images-h" }, "Dual images"));
  if (!done.length) {
    section.append(h("p", {}, "No finished reconstruction yet."));
    return section;
  }
  const channelNames = session.camera ? ["camera", "ambient"] : session.channels;
  const option = (r) => h("option", { value: r.id }, `#${r.id} ${r.method}`);
  const pick = h("select", { id: "image-recon" }, done.slice().reverse().map(option));
  const channelOptions = channelNames.map((c) => h("option", { value: c }, c));
  if (!session.camera && channelNames.length >= 3) channelOptions.push(h("option", { value: "__composite" }, "colour composite (first three)"));
  const channel = h("select", { id: "image-channel" }, channelOptions);
  const mode = h("select", { id: "image-mode" }, h("option", { value: "percentile" }, "percentile (0.5–99.5 %)"), h("option", { value: "linear" }, "linear (min–max)"));
  const compare = h("select", { id: "image-compare" }, h("option", { value: "" }, "nothing"), done.slice().reverse().map(option));
  const left = new ImageView("Dual image");
  const right = new ImageView("Compared");
  left.link(right);
  right.el.hidden = true;
  const cache = new Map();
  const load = async (id, ch) => {
    const key = `${id}/${ch}`;
    if (!cache.has(key)) cache.set(key, parseNpy(await bytes(`/v1/reconstructions/${id}/dual.npy?channel=${encodeURIComponent(ch)}`)));
    return cache.get(key);
  };
  const show = async (view, id) => {
    const ch = channel.value;
    let channels;
    let shape;
    if (ch === "__composite") {
      const imgs = await Promise.all(channelNames.slice(0, 3).map((c) => load(id, c)));
      channels = imgs.map((i) => i.data);
      shape = imgs[0].shape;
    } else {
      const img = await load(id, ch);
      channels = [img.data];
      shape = img.shape;
    }
    view.set(shape[1], shape[0], channels, mode.value, `#${id} ${ch === "__composite" ? "composite" : ch}`);
  };
  const refresh = async () => {
    try {
      await show(left, pick.value);
      right.el.hidden = !compare.value;
      if (compare.value) await show(right, compare.value);
      window.hz.dual = { id: Number(pick.value), hash: left.hash, draws: left.draws };
      say(`Showing reconstruction ${pick.value}`);
    } catch (e) {
      say(`Could not show the image: ${e.message}`, "error");
    }
  };
  for (const el of [pick, channel, mode, compare]) el.addEventListener("change", refresh);
  const dl = (ext) => h("button", { type: "button", id: `download-${ext}`, onclick: () => {
    const ch = channel.value === "__composite" ? channelNames[0] : channel.value;
    download(`/v1/reconstructions/${pick.value}/dual.${ext}?channel=${encodeURIComponent(ch)}${ext === "png" ? `&scale=${mode.value === "linear" ? "minmax" : "percentile"}` : ""}`, `dual-${pick.value}-${ch}.${ext}`)
      .catch((e) => say(e.message, "error"));
  } }, `Download ${ext.toUpperCase()}`);
  section.append(
    h("div", { class: "controls" },
      h("label", {}, "Reconstruction ", pick), h("label", {}, "Channel ", channel), h("label", {}, "Display ", mode), h("label", {}, "Side by side with ", compare)),
    h("div", { class: "pair" }, left.el, right.el),
    h("div", { class: "controls" }, dl("png"), dl("tiff"), dl("npy"),
      h("span", { class: "help" }, "Wheel or + / − to zoom, drag or arrow keys to pan; the two images move together.")));
  refresh();
  return section;
}

/** Little-endian float32 from base64 (the preview events' `values_f32le`). */
export function floatsOfBase64(b64) {
  const bin = atob(b64);
  const out = new Uint8Array(bin.length);
  for (let i = 0; i < bin.length; i++) out[i] = bin.charCodeAt(i);
  const view = new DataView(out.buffer);
  const values = new Float32Array(out.length / 4);
  for (let i = 0; i < values.length; i++) values[i] = view.getFloat32(4 * i, true);
  return values;
}

/**
 * The live preview of an uploading session: server-sent events of GET .../preview (a DGI,
 * zero-filled or raster image of the rows committed so far), drawn as they come until the final
 * one or until the page is left (`signal`).
 */
function previewPanel(session, signal) {
  const view = new ImageView("Live preview");
  const status = h("p", { id: "preview-status", role: "status" }, "Waiting for the first rows…");
  const section = h("section", { class: "card", id: "preview", "aria-labelledby": "preview-h" },
    h("h2", { id: "preview-h" }, "Live preview"), status, view.el);
  let frames = 0;
  const path = `/v1/sessions/${encodeURIComponent(session.id)}/preview?every_ms=500`;
  events(path, (name, f) => {
    if (name === "error") {
      status.textContent = `The preview stopped: ${f.detail}`;
      return;
    }
    if (name !== "preview") return;
    frames += 1;
    view.set(f.width, f.height, [floatsOfBase64(f.values_f32le)], "percentile", `${f.method}, ${f.rows.toLocaleString()} rows`);
    status.textContent = `${f.method} of ${f.rows.toLocaleString()} of ${f.expected_rows.toLocaleString()} rows${f.final ? " — every row is in" : ", updating as rows arrive"}`;
    window.hz.preview = { session: session.id, rows: f.rows, final: f.final, frames, hash: view.hash };
  }, signal).catch((e) => {
    if (e.name !== "AbortError") status.textContent = `No preview: ${e.message}`;
  });
  return section;
}

export async function sessionPage(main, id, signal, setTimer) {
  const session = await json(`/v1/sessions/${encodeURIComponent(id)}`, { signal });
  const { reconstructions } = await json(`/v1/sessions/${encodeURIComponent(id)}/reconstructions`, { signal });
  main.append(h("h1", { id: "session-title" }, `Session ${session.id}`));
  main.append(h("div", { class: "grid" }, detailsCard(session), h("section", { class: "card", "aria-labelledby": "recon-h" },
    h("h2", { id: "recon-h" }, "Reconstructions"), reconTable(reconstructions), plot(reconstructions))));
  main.append(imagesPanel(session, reconstructions));
  if (session.state === "open") main.append(previewPanel(session, signal));
  const latestDone = reconstructions.filter((r) => r.state === "done").pop();
  if (latestDone) {
    main.append(relightPanel(session, latestDone));
    if (session.camera) main.append(primalPanel(session, latestDone));
    if (!session.camera && session.directions.length >= 3) main.append(photometricPanel(session, latestDone));
  }
  main.append(await jobsPanel(session, signal));
  window.hz.session = { id: session.id, reconstructions: reconstructions.map((r) => r.id) };
}
