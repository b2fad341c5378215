// NumPy .npy files: what the server sends (float32/float64/uint16, C order) and what relight
// and primal take (float32).

export function npyHeader(u8) {
  if (u8[0] !== 0x93 || String.fromCharCode(...u8.slice(1, 6)) !== "NUMPY") throw new Error("not an NPY file");
  const major = u8[6];
  const dv = new DataView(u8.buffer, u8.byteOffset, u8.byteLength);
  const hlen = major === 1 ? dv.getUint16(8, true) : dv.getUint32(8, true);
  const start = major === 1 ? 10 : 12;
  const header = new TextDecoder().decode(u8.slice(start, start + hlen));
  const descr = /'descr':\s*'([^']+)'/.exec(header)[1];
  const shape = /'shape':\s*\(([^)]*)\)/.exec(header)[1].split(",").map((s) => s.trim()).filter(Boolean).map(Number);
  if (/'fortran_order':\s*True/.test(header)) throw new Error("Fortran order is not supported");
  return { descr, shape, headerBytes: start + hlen };
}

export function parseNpy(buf) {
  const u8 = buf instanceof Uint8Array ? buf : new Uint8Array(buf);
  const { descr, shape, headerBytes: offset } = npyHeader(u8);
  const count = shape.reduce((a, b) => a * b, 1);
  const body = u8.slice(offset, offset + count * { "<f4": 4, "<f8": 8, "<u2": 2 }[descr]).buffer;
  let data;
  if (descr === "<f4") data = new Float32Array(body);
  else if (descr === "<f8") data = Float32Array.from(new Float64Array(body));
  else if (descr === "<u2") data = Float32Array.from(new Uint16Array(body));
  else throw new Error(`dtype ${descr} is not supported`);
  return { shape, data, headerBytes: offset };
}

/** A float32 NPY of `shape` holding `data`. */
export function npyF32(shape, data) {
  const dims = shape.length === 1 ? `${shape[0]},` : shape.join(", ");
  let header = `{'descr': '<f4', 'fortran_order': False, 'shape': (${dims}), }`;
  const total = 10 + header.length + 1;
  header += " ".repeat((64 - (total % 64)) % 64) + "\n";
  const out = new Uint8Array(10 + header.length + data.length * 4);
  out.set([0x93, 0x4e, 0x55, 0x4d, 0x50, 0x59, 1, 0]);
  new DataView(out.buffer).setUint16(8, header.length, true);
  out.set(new TextEncoder().encode(header), 10);
  out.set(new Uint8Array(Float32Array.from(data).buffer), 10 + header.length);
  return out;
}
