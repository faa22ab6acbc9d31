// One map as the page holds it: cells loaded over the binary endpoint, kept current by the
// server's change stream (SSE) and "changed since version N" cell answers.
//
// Small maps are loaded whole. Large ones (at least `largeCells` cells with evidence) are
// loaded as an overview of coarsened cubes plus full-resolution cells in a box around the
// camera's target, refined again when the target moves.

import { CellStore } from './cells.js';
import { fetchCells, recentPoses, watch } from './api.js';

const MAX_POSES = 256;
const OVERVIEW_COARSEN = 2;
// Overviews coarser than a block (2^3 cells) cannot be patched per block: reload them, at most
// this often.
const OVERVIEW_RELOAD_MS = 5000;

export class MapModel {
  // `refineHalfWidth`: the full-resolution box reaches this far (m) from the camera's target.
  constructor(name, info, { largeCells, refineHalfWidth, onChange, onStatus }) {
    this.refineHalfWidth = refineHalfWidth;
    this.name = name;
    this.info = info;
    this.large = info.cells_with_evidence >= largeCells;
    this.onChange = onChange;
    this.onStatus = onStatus;
    this.store = new CellStore(); // the whole map, or the overview of a large one
    this.detail = null; // large maps: full-resolution cells inside `detailBox`
    this.detailBox = null;
    this.poses = [];
    this.syncing = false;
    this.dirty = false;
    this.stale = false; // set by a `reset` update: reload instead of patching
    this.lastOverview = 0;
    this.source = null;
    this.updates = 0;
    this.lastUpdateAt = 0;
  }

  get version() {
    return this.store.version;
  }

  get extent() {
    return this.store.extent;
  }

  async load(target) {
    if (this.large) {
      this.store.replaceAll(await fetchCells(this.name, { coarsen: OVERVIEW_COARSEN }));
      this.lastOverview = performance.now();
    } else {
      this.store.replaceAll(await fetchCells(this.name));
    }
    this.poses = (await recentPoses(this.name)).slice(-MAX_POSES);
    if (this.large) await this.refine(target || centreOf(this.store.extent));
    this.source = watch(this.name, this.store.version, (u) => this.onUpdate(u), this.onStatus);
    this.onChange();
  }

  close() {
    if (this.source) this.source.close();
  }

  // Large maps: full-resolution cells within a box around `target` (x, y; every z).
  async refine(target) {
    if (!this.large || !this.store.extent) return;
    const box = this.detailBoxAround(target);
    if (this.detailBox && Math.hypot(box.min[0] - this.detailBox.min[0], box.min[1] - this.detailBox.min[1]) < 1) return;
    const detail = new CellStore();
    detail.replaceAll(await fetchCells(this.name, box));
    this.detail = detail;
    this.detailBox = box;
    this.onChange();
  }

  detailBoxAround(target) {
    const e = this.store.extent;
    const h = this.refineHalfWidth;
    return { min: [target[0] - h, target[1] - h, e.min[2]], max: [target[0] + h, target[1] + h, e.max[2] - 1e-3] };
  }

  onUpdate(update) {
    this.updates += 1;
    this.lastUpdateAt = performance.now();
    if (update.poses.length) this.poses = this.poses.concat(update.poses).slice(-MAX_POSES);
    // The server restarted since the version held: it cannot say which blocks went away.
    if (update.reset) this.stale = true;
    if (update.reset || update.version > this.store.version) this.sync();
    else this.onChange();
  }

  // Fetches what changed since the version held; coalesces updates that arrive meanwhile.
  async sync() {
    if (this.syncing) {
      this.dirty = true;
      return;
    }
    this.syncing = true;
    try {
      do {
        this.dirty = false;
        await this.syncOnce();
        this.onChange();
      } while (this.dirty);
    } catch (e) {
      this.onStatus(`update failed: ${e.message}`);
    } finally {
      this.syncing = false;
    }
  }

  async syncOnce() {
    try {
      if (this.stale) await this.reload();
      else await this.patch();
    } catch (e) {
      // 410: changes since our version are not known (the server restarted): reload.
      if (e.status !== 410) throw e;
      await this.reload();
    }
  }

  // Replaces everything held with the server's current cells.
  async reload() {
    this.stale = false;
    this.store.replaceAll(await fetchCells(this.name, this.large ? { coarsen: OVERVIEW_COARSEN } : {}));
    this.lastOverview = performance.now();
    if (this.detail) this.detail.replaceAll(await fetchCells(this.name, this.detailBox));
  }

  // Fetches the cells of the blocks changed since the version held.
  async patch() {
    const since = this.store.version;
    if (!this.large || this.store.coarsen <= 3) {
      this.store.applyChanges(await fetchCells(this.name, { since, coarsen: this.store.coarsen }));
    } else if (performance.now() - this.lastOverview > OVERVIEW_RELOAD_MS) {
      this.store.replaceAll(await fetchCells(this.name, { coarsen: OVERVIEW_COARSEN }));
      this.lastOverview = performance.now();
    } else {
      this.dirty = true;
      await new Promise((r) => setTimeout(r, OVERVIEW_RELOAD_MS));
    }
    if (this.detail) {
      this.detail.applyChanges(await fetchCells(this.name, { since: this.detail.version, ...this.detailBox }));
    }
  }

  // Every cell to draw: overview cubes outside the detail box plus the detail cells.
  flat() {
    const base = this.store.flat();
    if (!this.detail) return base;
    const fine = this.detail.flat();
    const { min, max } = this.detailBox;
    const keep = [];
    for (let i = 0; i < base.n; i++) {
      const x = base.centres[3 * i];
      const y = base.centres[3 * i + 1];
      if (x < min[0] || x > max[0] || y < min[1] || y > max[1]) keep.push(i);
    }
    const n = keep.length + fine.n;
    const out = {
      n,
      centres: new Float32Array(3 * n),
      sizes: new Float32Array(n),
      probability: new Float64Array(n),
      variance: new Float64Array(n),
    };
    keep.forEach((src, j) => {
      out.centres.set(base.centres.subarray(3 * src, 3 * src + 3), 3 * j);
      out.sizes[j] = base.sizes[src];
      out.probability[j] = base.probability[src];
      out.variance[j] = base.variance[src];
    });
    out.centres.set(fine.centres, 3 * keep.length);
    out.sizes.set(fine.sizes, keep.length);
    out.probability.set(fine.probability, keep.length);
    out.variance.set(fine.variance, keep.length);
    return out;
  }
}

function centreOf(extent) {
  return [0, 1, 2].map((i) => (extent.min[i] + extent.max[i]) / 2);
}
