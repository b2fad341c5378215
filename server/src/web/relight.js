// Relighting, interactive: draw a light on the camera's view (disc, brush, stripe, or an uploaded
// image) or move one slider per detector, and the relit dual image follows. While one request
// is in flight only the newest wanted light waits (older ones are dropped), so the image keeps
// up with the pointer instead of queueing behind it. Each drawn image records the time from the
// input event that asked for it to the image drawn (window.hz.relight; docs/web-viewer.md).
// Also: the primal prediction of a stored pattern beside the measured frame, and photometric
// normals and albedo.

import { request, imageUrl } from "./api.js";
import { h, say, fmt } from "./dom.js";
import { parseNpy, npyF32, npyHeader } from "./npy.js";
import { ImageView } from "./image.js";

function relighter(rec, view, mode) {
  const stats = { drawn: 0, timings: [], hashes: [], wanted: 0, answered: 0, errors: 0, inFlight: false };
  window.hz.relight = stats;
  let pending = null;
  const pump = async () => {
    if (stats.inFlight || !pending) return;
    const job = pending;
    pending = null;
    stats.inFlight = true;
    try {
      const sent = performance.now();
      const r = await request(`/v1/reconstructions/${rec.id}/relight?format=npy`, { method: "POST", body: job.body, type: job.type });
      const body = new Uint8Array(await r.arrayBuffer());
      const received = performance.now();
      const img = parseNpy(body);
      view.set(img.shape[1], img.shape[0], [img.data], mode(), `Relit dual image (#${rec.id})`);
      const drawn = performance.now();
      stats.drawn += 1;
      // From the input event to the image drawn, and its parts: the event reaching the
      // handler, waiting for an earlier request, the request's round trip, decoding and drawing.
      stats.timings.push({
        ms: drawn - job.t, kind: job.kind, toHandler: job.handled - job.t, waited: sent - job.handled,
        network: received - sent, draw: drawn - received, serverTiming: r.headers.get("server-timing"),
      });
      stats.hashes.push(view.hash);
      stats.answered = job.seq;
      view.canvas.dataset.drawn = String(stats.drawn);
    } catch (e) {
      if (e.status === 429) {
        // Over the token's request rate: try the newest light again in a second.
        stats.limited = (stats.limited || 0) + 1;
        if (!pending) pending = job;
        say("Relight: over this token's request rate; retrying", "error");
        setTimeout(() => { stats.inFlight = false; pump(); }, 1000);
        return;
      }
      stats.errors += 1;
      stats.answered = job.seq;
      stats.lastError = e.message;
      say(`Relight: ${e.message}`, "error");
    }
    stats.inFlight = false;
    pump();
  };
  return (body, type, event) => {
    stats.wanted += 1;
    const handled = performance.now();
    pending = { body, type, t: event ? event.timeStamp : handled, handled, kind: event ? event.type : "control", seq: stats.wanted };
    pump();
  };
}

const lightJson = (light) => JSON.stringify({ light });

function cameraRelight(session, rec) {
  const cw = session.camera.width;
  const ch = session.camera.height;
  const pw = session.patterns.width;
  const ph = session.patterns.height;
  const cameraView = new ImageView("Camera view: draw the light here");
  cameraView.interactive = false;
  cameraView.canvas.id = "camera-view";
  const relit = new ImageView("Relit dual image");
  relit.canvas.id = "relit";
  const mode = h("select", { id: "relight-mode" }, h("option", { value: "percentile" }, "percentile"), h("option", { value: "linear" }, "linear"));
  const tool = h("select", { id: "relight-tool" }, ["disc", "brush", "stripe"].map((t) => h("option", { value: t }, t)));
  const radius = h("input", { id: "relight-radius", type: "range", min: 1, max: Math.max(2, Math.round(Math.max(cw, ch) / 2)), step: 0.5, value: Math.max(1, Math.round(Math.min(cw, ch) / 6)) });
  const file = h("input", { id: "relight-file", type: "file", accept: "image/*" });
  const want = relighter(rec, relit, () => mode.value);
  const mask = new Float32Array(cw * ch);
  const overlay = document.createElement("canvas");
  overlay.width = cw;
  overlay.height = ch;
  const drawOverlay = (weights) => {
    const img = new ImageData(cw, ch);
    for (let i = 0; i < cw * ch; i++) {
      img.data[4 * i] = 255;
      img.data[4 * i + 1] = 210;
      img.data[4 * i + 2] = 0;
      img.data[4 * i + 3] = Math.round(255 * Math.min(1, Math.max(0, weights[i])));
    }
    overlay.getContext("2d").putImageData(img, 0, 0);
    cameraView.render(overlay);
  };
  const discWeights = (x, y, r, into = new Float32Array(cw * ch)) => {
    for (let j = 0; j < ch; j++) for (let i = 0; i < cw; i++) if ((i + 0.5 - x) ** 2 + (j + 0.5 - y) ** 2 <= r * r) into[j * cw + i] = 1;
    return into;
  };
  let stroke = null;
  const apply = (e) => {
    let [x, y] = cameraView.toImage(e.clientX, e.clientY);
    x = Math.min(cw - 0.5, Math.max(0.5, x));
    y = Math.min(ch - 0.5, Math.max(0.5, y));
    const r = Number(radius.value);
    if (tool.value === "disc") {
      want(lightJson({ preset: "disc", x, y, radius: r }), "application/json", e);
      drawOverlay(discWeights(x, y, r));
    } else if (tool.value === "stripe") {
      if (e.type === "pointerdown") stroke = x;
      let x0 = Math.floor(Math.min(stroke, x));
      let x1 = Math.ceil(Math.max(stroke, x));
      if (x1 <= x0) x1 = x0 + 1;
      want(lightJson({ preset: "stripe", x0, x1 }), "application/json", e);
      const w = new Float32Array(cw * ch);
      for (let j = 0; j < ch; j++) for (let i = x0; i < x1; i++) w[j * cw + i] = 1;
      drawOverlay(w);
    } else {
      if (e.type === "pointerdown" && !e.shiftKey) mask.fill(0);
      discWeights(x, y, r, mask);
      want(npyF32([ch, cw], mask), "application/x-npy", e);
      drawOverlay(mask);
    }
  };
  let down = false;
  const c = cameraView.canvas;
  c.addEventListener("pointerdown", (e) => {
    down = true;
    c.setPointerCapture(e.pointerId);
    apply(e);
  });
  c.addEventListener("pointermove", (e) => down && apply(e));
  c.addEventListener("pointerup", () => (down = false));
  c.addEventListener("pointercancel", () => (down = false));
  // Keyboard: arrows move a disc light from the centre.
  let kx = cw / 2;
  let ky = ch / 2;
  c.addEventListener("keydown", (e) => {
    const d = { ArrowLeft: [-1, 0], ArrowRight: [1, 0], ArrowUp: [0, -1], ArrowDown: [0, 1] }[e.key];
    if (!d) return;
    e.preventDefault();
    kx = Math.min(cw - 0.5, Math.max(0.5, kx + d[0]));
    ky = Math.min(ch - 0.5, Math.max(0.5, ky + d[1]));
    const r = Number(radius.value);
    want(lightJson({ preset: "disc", x: kx, y: ky, radius: r }), "application/json", e);
    drawOverlay(discWeights(kx, ky, r));
  });
  file.addEventListener("change", async () => {
    const f = file.files[0];
    if (!f) return;
    const bitmap = await createImageBitmap(f);
    const small = document.createElement("canvas");
    small.width = cw;
    small.height = ch;
    const ctx = small.getContext("2d");
    ctx.drawImage(bitmap, 0, 0, cw, ch);
    const px = ctx.getImageData(0, 0, cw, ch).data;
    for (let i = 0; i < cw * ch; i++) mask[i] = (0.2126 * px[4 * i] + 0.7152 * px[4 * i + 1] + 0.0722 * px[4 * i + 2]) / 255;
    want(npyF32([ch, cw], mask), "application/x-npy");
    drawOverlay(mask);
  });
  const full = h("button", { type: "button", id: "relight-full", onclick: () => {
    want(lightJson({ preset: "full" }), "application/json");
    drawOverlay(new Float32Array(cw * ch).fill(1));
  } }, "Whole camera");
  mode.addEventListener("change", () => want(lightJson({ preset: "full" }), "application/json"));
  // The camera's view under the whole projector: T 1 (+ ambient), the primal of a white pattern.
  (async () => {
    try {
      const r = await request(`/v1/reconstructions/${rec.id}/primal?format=npy`, { method: "POST", body: npyF32([ph, pw], new Float32Array(pw * ph).fill(1)), type: "application/x-npy" });
      const img = parseNpy(new Uint8Array(await r.arrayBuffer()));
      cameraView.set(img.shape[1], img.shape[0], [img.data], "percentile", `Camera view under the whole projector (T·1), #${rec.id}`);
      c.dataset.ready = "1";
      drawOverlay(new Float32Array(cw * ch).fill(1));
      want(lightJson({ preset: "full" }), "application/json");
    } catch (e) {
      say(`Camera view: ${e.message}`, "error");
    }
  })();
  return h("section", { class: "card", id: "relight-panel", "aria-labelledby": "relight-h" },
    h("h2", { id: "relight-h" }, "Relighting"),
    h("p", { class: "help" }, "Press and drag on the camera view to place the virtual light (the arrow keys move a disc); the dual image lit by it updates as you drag. Brush strokes add up while Shift is held."),
    h("div", { class: "controls" }, h("label", {}, "Tool ", tool), h("label", {}, "Radius (camera px) ", radius), h("label", {}, "Light from an image ", file), full, h("label", {}, "Display ", mode)),
    h("div", { class: "pair" }, cameraView.el, relit.el));
}

function detectorRelight(session, rec) {
  const relit = new ImageView("Relit dual image");
  relit.canvas.id = "relit";
  const mode = h("select", { id: "relight-mode" }, h("option", { value: "percentile" }, "percentile"), h("option", { value: "linear" }, "linear"));
  const want = relighter(rec, relit, () => mode.value);
  const sliders = session.channels.map((c) => h("input", { type: "range", min: 0, max: 1, step: 0.01, value: 1, "data-channel": c, id: `weight-${c}` }));
  const send = (e) => {
    const weights = {};
    sliders.forEach((s) => (weights[s.dataset.channel] = Number(s.value)));
    want(lightJson({ weights }), "application/json", e);
  };
  sliders.forEach((s) => s.addEventListener("input", send));
  mode.addEventListener("change", send);
  send();
  return h("section", { class: "card", id: "relight-panel", "aria-labelledby": "relight-h" },
    h("h2", { id: "relight-h" }, "Relighting"),
    h("p", { class: "help" }, "One weight per detector: the dual image lit from those detectors."),
    h("div", { class: "controls" }, sliders.map((s) => h("label", {}, `${s.dataset.channel} `, s)), h("label", {}, "Display ", mode)),
    h("div", { class: "pair" }, relit.el));
}

export function relightPanel(session, rec) {
  return session.camera ? cameraRelight(session, rec) : detectorRelight(session, rec);
}

/** Row `row` of a camera session's stored frames, read from the start of measurements.npy. */
async function measuredFrame(session, row) {
  const r = await request(`/v1/sessions/${encodeURIComponent(session.id)}/measurements.npy`);
  const reader = r.body.getReader();
  const pixels = session.camera.width * session.camera.height;
  const bytesPer = session.camera.format === "u16" ? 2 : 4;
  let buf = new Uint8Array(0);
  let need = Infinity;
  while (buf.length < need) {
    const { value, done } = await reader.read();
    if (done) break;
    const next = new Uint8Array(buf.length + value.length);
    next.set(buf);
    next.set(value, buf.length);
    buf = next;
    if (need === Infinity && buf.length >= 12) {
      const hlen = buf[6] === 1 ? buf[8] | (buf[9] << 8) : new DataView(buf.buffer).getUint32(8, true);
      need = (buf[6] === 1 ? 10 : 12) + hlen + (row + 1) * pixels * bytesPer;
    }
  }
  reader.cancel().catch(() => {});
  const header = npyHeader(buf).headerBytes;
  const start = header + row * pixels * bytesPer;
  const raw = buf.slice(start, start + pixels * bytesPer).buffer;
  return bytesPer === 2 ? Float32Array.from(new Uint16Array(raw)) : new Float32Array(raw);
}

export function primalPanel(session, rec) {
  const index = h("input", { id: "primal-index", type: "number", min: 0, max: session.patterns.count - 1, value: 1 });
  const predicted = new ImageView("Predicted camera image");
  const measured = new ImageView("Measured frame");
  predicted.link(measured);
  predicted.canvas.id = "primal-predicted";
  measured.canvas.id = "primal-measured";
  const out = h("p", { id: "primal-error", "aria-live": "polite" });
  const go = async () => {
    try {
      const r = await request(`/v1/reconstructions/${rec.id}/primal?format=npy`, { method: "POST", body: JSON.stringify({ pattern_index: Number(index.value) }), type: "application/json" });
      const img = parseNpy(new Uint8Array(await r.arrayBuffer()));
      predicted.set(img.shape[1], img.shape[0], [img.data], "linear", `Predicted T·p + ambient, pattern ${index.value}`);
      const rowHeader = r.headers.get("x-helmholtz-measured-row");
      const err = r.headers.get("x-helmholtz-relative-error");
      const psnr = r.headers.get("x-helmholtz-psnr-db");
      if (rowHeader !== null) {
        const frame = await measuredFrame(session, Number(rowHeader));
        measured.set(img.shape[1], img.shape[0], [frame], "linear", `Measured frame (row ${rowHeader})`);
        out.textContent = `Pattern ${index.value}: relative error ${fmt(Number(err))}, PSNR ${fmt(Number(psnr))} dB against the measured frame (row ${rowHeader}).`;
      } else {
        out.textContent = `Pattern ${index.value}: no stored frame to compare with.`;
      }
    } catch (e) {
      out.textContent = e.message;
    }
  };
  const button = h("button", { type: "button", id: "primal-go", onclick: go }, "Predict");
  return h("section", { class: "card", id: "primal-panel", "aria-labelledby": "primal-h" },
    h("h2", { id: "primal-h" }, "Primal prediction"),
    h("div", { class: "controls" }, h("label", {}, "Stored pattern index ", index), button),
    out,
    h("div", { class: "pair" }, predicted.el, measured.el));
}

export function photometricPanel(session, rec) {
  const section = h("section", { class: "card", id: "photometric-panel", "aria-labelledby": "photo-h" }, h("h2", { id: "photo-h" }, "Photometric stereo"));
  const figs = h("div", { class: "pair" });
  section.append(figs);
  for (const [file, alt] of [["normals.png", "Surface normals (x, y, z as red, green, blue)"], ["albedo.png", "Albedo"]]) {
    const img = h("img", { alt, class: "photo" });
    figs.append(h("figure", {}, img, h("figcaption", {}, alt)));
    imageUrl(`/v1/reconstructions/${rec.id}/${file}`).then((u) => (img.src = u)).catch((e) => img.replaceWith(h("p", { class: "error" }, `${file}: ${e.message}`)));
  }
  return section;
}
