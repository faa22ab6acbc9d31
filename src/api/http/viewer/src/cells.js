// Cells as the page holds them: the decoder of the server's binary answer
// (GET /v1/maps/{map}/cells, layout documented in src/api/http/viewer.rs), the state rule, and a
// store that keeps cells per block so a "changed since version N" answer replaces exactly the
// blocks it lists.

export const FREE = 0;
export const OCCUPIED = 1;
export const UNKNOWN = 2;
export const STATE_NAMES = ['free', 'occupied', 'unknown'];

// The server's state rule (CellEstimate::from_evidence in src/core/map.rs), applied to the
// server's own f64 probability and variance, so it agrees with the server for any thresholds.
export function classify(p, v, th) {
  if (p < th.p_free && v < th.var_max) return FREE;
  if (p > th.p_occ && v < th.var_max) return OCCUPIED;
  return UNKNOWN;
}

const HEADER_BYTES = 64;

// Typed-array views straight over the answer (x86 and ARM browsers are little-endian, as the
// format is).
export function decodeCells(buffer) {
  const dv = new DataView(buffer);
  const magic = String.fromCharCode(...new Uint8Array(buffer, 0, 4));
  if (magic !== 'BGKC') throw new Error(`cells answer: bad magic ${JSON.stringify(magic)}`);
  const layout = dv.getUint32(4, true);
  if (layout !== 1) throw new Error(`cells answer: unknown layout version ${layout}`);
  const n = dv.getUint32(8, true);
  const m = dv.getUint32(12, true);
  const expected = HEADER_BYTES + 32 * n + 12 * m;
  if (buffer.byteLength !== expected) {
    throw new Error(`cells answer: ${buffer.byteLength} bytes, expected ${expected}`);
  }
  const f32 = (off) => dv.getFloat32(off, true);
  let off = HEADER_BYTES;
  const take = (Type, count) => {
    const a = new Type(buffer, off, count);
    off += count * Type.BYTES_PER_ELEMENT;
    return a;
  };
  return {
    version: Number(dv.getBigUint64(16, true)),
    resolution: dv.getFloat64(24, true),
    coarsen: dv.getUint32(32, true),
    blockEdge: dv.getUint32(36, true),
    extent: { min: [f32(40), f32(44), f32(48)], max: [f32(52), f32(56), f32(60)] },
    n,
    centres: take(Float32Array, 3 * n),
    sizes: take(Float32Array, n),
    probability: take(Float64Array, n),
    variance: take(Float64Array, n),
    blocks: take(Int32Array, 3 * m),
  };
}

// One number per block key (17 bits per axis: ±65536 blocks, ±52 km at 0.1 m cells).
const OFFSET = 65536;
const SPAN = 131072;
function packKey(x, y, z) {
  return ((x + OFFSET) * SPAN + (y + OFFSET)) * SPAN + (z + OFFSET);
}

// Cells grouped by block; `flat()` concatenates them for drawing.
export class CellStore {
  constructor() {
    this.blocks = new Map();
    this.version = 0;
    this.resolution = 0.1;
    this.coarsen = 0;
    this.extent = null;
    this.cached = null;
  }

  // Replaces everything with a full answer.
  replaceAll(answer) {
    this.blocks.clear();
    this.addCells(answer);
  }

  // Applies a `since` answer: drops the listed blocks, then adds their current cells.
  applyChanges(answer) {
    for (let i = 0; i < answer.blocks.length; i += 3) {
      this.blocks.delete(packKey(answer.blocks[i], answer.blocks[i + 1], answer.blocks[i + 2]));
    }
    this.addCells(answer);
  }

  addCells(a) {
    this.version = a.version;
    this.resolution = a.resolution;
    this.coarsen = a.coarsen;
    this.extent = a.extent;
    const blockM = a.resolution * a.blockEdge;
    const groups = new Map();
    for (let i = 0; i < a.n; i++) {
      const c = a.centres;
      const key = packKey(
        Math.floor(c[3 * i] / blockM),
        Math.floor(c[3 * i + 1] / blockM),
        Math.floor(c[3 * i + 2] / blockM),
      );
      let g = groups.get(key);
      if (!g) groups.set(key, (g = []));
      g.push(i);
    }
    for (const [key, idx] of groups) {
      const k = idx.length;
      const part = {
        n: k,
        centres: new Float32Array(3 * k),
        sizes: new Float32Array(k),
        probability: new Float64Array(k),
        variance: new Float64Array(k),
      };
      idx.forEach((src, j) => {
        part.centres.set(a.centres.subarray(3 * src, 3 * src + 3), 3 * j);
        part.sizes[j] = a.sizes[src];
        part.probability[j] = a.probability[src];
        part.variance[j] = a.variance[src];
      });
      this.blocks.set(key, part);
    }
    this.cached = null;
  }

  // Every cell, as parallel arrays (cached until the next change).
  flat() {
    if (this.cached) return this.cached;
    let n = 0;
    for (const b of this.blocks.values()) n += b.n;
    const out = {
      n,
      centres: new Float32Array(3 * n),
      sizes: new Float32Array(n),
      probability: new Float64Array(n),
      variance: new Float64Array(n),
    };
    let at = 0;
    for (const b of this.blocks.values()) {
      out.centres.set(b.centres, 3 * at);
      out.sizes.set(b.sizes, at);
      out.probability.set(b.probability, at);
      out.variance.set(b.variance, at);
      at += b.n;
    }
    this.cached = out;
    return out;
  }
}
