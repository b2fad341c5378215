// Float images on a canvas: grey (one channel) or colour (three), linear (min..max) or
// percentile (0.5..99.5 %) display, zoom (wheel, + / - keys or buttons) and pan (drag, arrow keys).
// Views can be linked so two images side by side zoom and pan together.

export function range(data, mode) {
  const finite = [];
  for (const v of data) if (Number.isFinite(v)) finite.push(v);
  if (!finite.length) return [0, 1];
  if (mode === "percentile") {
    finite.sort((a, b) => a - b);
    const at = (q) => finite[Math.min(finite.length - 1, Math.max(0, Math.round(q * (finite.length - 1))))];
    return [at(0.005), at(0.995)];
  }
  let lo = Infinity;
  let hi = -Infinity;
  for (const v of finite) {
    if (v < lo) lo = v;
    if (v > hi) hi = v;
  }
  return [lo, hi];
}

function toByte(v, lo, hi) {
  if (!Number.isFinite(v)) return 0;
  const t = hi > lo ? (v - lo) / (hi - lo) : 0.5;
  return Math.max(0, Math.min(255, Math.round(t * 255)));
}

/** RGBA pixels of grey `data` or colour `[r, g, b]` (one common range for colour). */
export function rgba(width, height, channels, mode) {
  const all = channels.length === 1 ? channels[0] : Float32Array.from(channels.flatMap((c) => Array.from(c)));
  const [lo, hi] = range(all, mode);
  const out = new ImageData(width, height);
  const px = out.data;
  const n = width * height;
  for (let i = 0; i < n; i++) {
    const r = toByte(channels[0][i], lo, hi);
    px[4 * i] = r;
    px[4 * i + 1] = channels.length === 1 ? r : toByte(channels[1][i], lo, hi);
    px[4 * i + 2] = channels.length === 1 ? r : toByte(channels[2][i], lo, hi);
    px[4 * i + 3] = 255;
  }
  return { image: out, lo, hi };
}

/** A 32-bit FNV-1a hash of a float image (tests compare drawn images by it). */
export function hash(data) {
  const u8 = new Uint8Array(data.buffer, data.byteOffset, data.byteLength);
  let h = 0x811c9dc5;
  for (let i = 0; i < u8.length; i++) {
    h ^= u8[i];
    h = Math.imul(h, 0x01000193);
  }
  return (h >>> 0).toString(16);
}

export class ImageView {
  constructor(label, { size = 384 } = {}) {
    this.el = document.createElement("figure");
    this.el.className = "imageview";
    this.canvas = document.createElement("canvas");
    this.canvas.width = size;
    this.canvas.height = size;
    this.canvas.tabIndex = 0;
    this.canvas.setAttribute("role", "img");
    this.canvas.setAttribute("aria-label", label);
    this.caption = document.createElement("figcaption");
    this.caption.textContent = label;
    const tools = document.createElement("div");
    tools.className = "zoomtools";
    for (const [text, title, f] of [
      ["+", "Zoom in", () => this.zoomBy(1.5)],
      ["−", "Zoom out", () => this.zoomBy(1 / 1.5)],
      ["1:1", "Fit the image", () => this.reset()],
    ]) {
      const b = document.createElement("button");
      b.type = "button";
      b.textContent = text;
      b.title = title;
      b.setAttribute("aria-label", title);
      b.addEventListener("click", f);
      tools.append(b);
    }
    this.el.append(this.canvas, tools, this.caption);
    this.source = document.createElement("canvas");
    this.zoom = 1;
    this.panX = 0;
    this.panY = 0;
    this.linked = [];
    this.label = label;
    this.hash = null;
    this.draws = 0;
    this.interactive = true;
    this.#listen();
  }

  link(other) {
    this.linked.push(other);
    other.linked.push(this);
  }

  /** Shows `channels` (one grey or three colour Float32Arrays) of `width` x `height`. */
  set(width, height, channels, mode, caption) {
    const { image, lo, hi } = rgba(width, height, channels, mode);
    if (this.source.width !== width || this.source.height !== height) {
      this.source.width = width;
      this.source.height = height;
    }
    this.source.getContext("2d").putImageData(image, 0, 0);
    this.width = width;
    this.height = height;
    this.hash = hash(channels[0]);
    this.draws += 1;
    this.canvas.dataset.hash = this.hash;
    this.canvas.dataset.draws = String(this.draws);
    this.caption.textContent = `${caption || this.label} — ${width}×${height}, ${mode} display [${lo.toPrecision(3)}, ${hi.toPrecision(3)}]`;
    this.render();
  }

  /** The canvas position (CSS pixels) of image pixel coordinates, and back. */
  fit() {
    const s = Math.min(this.canvas.width / this.width, this.canvas.height / this.height);
    return s * this.zoom;
  }

  toImage(clientX, clientY) {
    const rect = this.canvas.getBoundingClientRect();
    const cx = ((clientX - rect.left) * this.canvas.width) / rect.width;
    const cy = ((clientY - rect.top) * this.canvas.height) / rect.height;
    const s = this.fit();
    const ox = (this.canvas.width - this.width * s) / 2 + this.panX;
    const oy = (this.canvas.height - this.height * s) / 2 + this.panY;
    return [(cx - ox) / s, (cy - oy) / s];
  }

  render(overlay) {
    if (!this.width) return;
    const ctx = this.canvas.getContext("2d");
    ctx.setTransform(1, 0, 0, 1, 0, 0);
    ctx.fillStyle = "#222";
    ctx.fillRect(0, 0, this.canvas.width, this.canvas.height);
    const s = this.fit();
    const ox = (this.canvas.width - this.width * s) / 2 + this.panX;
    const oy = (this.canvas.height - this.height * s) / 2 + this.panY;
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(this.source, ox, oy, this.width * s, this.height * s);
    if (overlay) {
      ctx.imageSmoothingEnabled = false;
      ctx.globalAlpha = 0.45;
      ctx.drawImage(overlay, ox, oy, this.width * s, this.height * s);
      ctx.globalAlpha = 1;
    }
    this.overlay = overlay;
  }

  #sync() {
    for (const v of this.linked) {
      v.zoom = this.zoom;
      v.panX = this.panX;
      v.panY = this.panY;
      v.render(v.overlay);
    }
    this.render(this.overlay);
  }

  zoomBy(f) {
    this.zoom = Math.min(64, Math.max(0.25, this.zoom * f));
    this.panX *= f;
    this.panY *= f;
    this.#sync();
  }

  reset() {
    this.zoom = 1;
    this.panX = 0;
    this.panY = 0;
    this.#sync();
  }

  #listen() {
    this.canvas.addEventListener("wheel", (e) => {
      if (!this.interactive) return;
      e.preventDefault();
      this.zoomBy(e.deltaY < 0 ? 1.25 : 0.8);
    }, { passive: false });
    let drag = null;
    this.canvas.addEventListener("pointerdown", (e) => {
      if (!this.interactive) return;
      drag = { x: e.clientX, y: e.clientY, px: this.panX, py: this.panY };
      this.canvas.setPointerCapture(e.pointerId);
    });
    this.canvas.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const rect = this.canvas.getBoundingClientRect();
      const k = this.canvas.width / rect.width;
      this.panX = drag.px + (e.clientX - drag.x) * k;
      this.panY = drag.py + (e.clientY - drag.y) * k;
      this.#sync();
    });
    const end = () => (drag = null);
    this.canvas.addEventListener("pointerup", end);
    this.canvas.addEventListener("pointercancel", end);
    this.canvas.addEventListener("keydown", (e) => {
      if (!this.interactive) return;
      const step = 20;
      const keys = {
        "+": () => this.zoomBy(1.5), "=": () => this.zoomBy(1.5), "-": () => this.zoomBy(1 / 1.5), "0": () => this.reset(),
        ArrowLeft: () => { this.panX += step; this.#sync(); }, ArrowRight: () => { this.panX -= step; this.#sync(); },
        ArrowUp: () => { this.panY += step; this.#sync(); }, ArrowDown: () => { this.panY -= step; this.#sync(); },
      };
      if (keys[e.key]) {
        e.preventDefault();
        keys[e.key]();
      }
    });
  }
}
