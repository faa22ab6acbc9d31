// The bgkmap viewer page: wires the map model, the 3D scene and the side panel together.
//
// Test hooks: `window.__viewerReady` turns true after the first map is drawn, and
// `window.__viewer` reports what is on screen (see `publish`).

import { boxCounts, castRay, cellAt, listMaps } from './api.js';
import { classify, FREE, OCCUPIED, STATE_NAMES, UNKNOWN } from './cells.js';
import { ramp, renderLegend, scaleFor } from './colour.js';
import { MapModel } from './model.js';
import { MapScene } from './scene.js';

const $ = (id) => document.getElementById(id);
const params = new URLSearchParams(location.search);
// Maps with at least this many cells are drawn coarse, refined within REFINE_M of the camera's
// target (both can be set in the URL: `?large=…&refine=…`).
const LARGE_CELLS = Number(params.get('large') || 1_000_000);
const REFINE_M = Number(params.get('refine') || 4);
// The var_max slider: 100 steps over [0, 0.25] (a Beta variance never exceeds ¼), then "off".
const VAR_STEPS = 100;
const VAR_STEP = 0.0025;

const ui = {
  scene: new MapScene($('view')),
  model: null,
  flat: null,
  classes: new Uint8Array(0),
  counts: [0, 0, 0],
  thresholds: { p_free: 0.3, p_occ: 0.7, var_max: 100 },
  varOff: 100,
  tool: 'inspect',
  clicks: [],
  info: null,
  box: null,
  ray: null,
  status: 'loading',
  errors: [],
};
window.__viewer = { ready: false };

function setStatus(text) {
  ui.status = text;
  $('status').textContent = text;
  publish();
}

function fail(e) {
  ui.errors.push(String(e.message || e));
  setStatus(`error: ${e.message || e}`);
}

// ---------------------------------------------------------------------------------------------
// Thresholds, classes, drawing

function readThresholds() {
  const pFree = Number($('p-free').value);
  const pOcc = Number($('p-occ').value);
  const v = Number($('var-max').value);
  ui.thresholds = {
    p_free: Math.min(pFree, pOcc),
    p_occ: Math.max(pFree, pOcc),
    var_max: v >= VAR_STEPS ? ui.varOff : v * VAR_STEP,
  };
  $('p-free-value').textContent = ui.thresholds.p_free.toFixed(2);
  $('p-occ-value').textContent = ui.thresholds.p_occ.toFixed(2);
  $('var-max-value').textContent = v >= VAR_STEPS ? `off (${ui.varOff})` : ui.thresholds.var_max.toFixed(4);
}

function setThresholdInputs(th) {
  $('p-free').value = th.p_free;
  $('p-occ').value = th.p_occ;
  ui.varOff = Math.max(th.var_max, 0.25);
  $('var-max').value = th.var_max >= 0.25 ? VAR_STEPS : Math.round(th.var_max / VAR_STEP);
  readThresholds();
}

function classifyAll() {
  const f = ui.flat;
  ui.classes = new Uint8Array(f.n);
  ui.counts = [0, 0, 0];
  for (let i = 0; i < f.n; i++) {
    const c = classify(f.probability[i], f.variance[i], ui.thresholds);
    ui.classes[i] = c;
    ui.counts[c]++;
  }
}

function draw() {
  if (!ui.model) return;
  const t0 = performance.now();
  ui.flat = ui.model.flat();
  classifyAll();
  const scale = scaleFor($('colour').value, ui.model.extent);
  renderLegend($('legend'), scale);
  const span = scale.hi - scale.lo || 1;
  const shown = { [OCCUPIED]: true, [FREE]: $('show-free').checked, [UNKNOWN]: $('show-unknown').checked };
  ui.scene.setCells(ui.flat, ui.classes, shown, (i, out, at) => ramp((scale.value(ui.flat, i) - scale.lo) / span, out, at));
  ui.scene.setPoses(ui.model.poses);
  $('counts').textContent =
    `${ui.counts[OCCUPIED]} occupied · ${ui.counts[FREE]} free · ${ui.counts[UNKNOWN]} unknown` +
    (ui.model.large ? ` · overview coarsened ×${2 ** ui.model.store.coarsen}` : '');
  $('version').textContent = `version ${ui.model.version}`;
  ui.drawMs = performance.now() - t0;
  publish();
}

// ---------------------------------------------------------------------------------------------
// Maps

async function openMap(name, info) {
  if (ui.model) ui.model.close();
  ui.info = ui.box = ui.ray = null;
  ui.scene.clearMarkers();
  setThresholdInputs(info.params);
  const model = new MapModel(name, info, {
    largeCells: LARGE_CELLS,
    refineHalfWidth: REFINE_M,
    onChange: () => ui.model === model && draw(),
    onStatus: (s) => ui.model === model && setStatus(s),
  });
  ui.model = model;
  setStatus('loading');
  await model.load(null);
  if (model.extent) ui.scene.frame(model.extent);
  draw();
}

async function start() {
  const maps = await listMaps();
  const picker = $('map');
  picker.innerHTML = '';
  for (const m of maps) picker.add(new Option(`${m.map} (${m.cells_with_evidence} cells)`, m.map));
  const wanted = params.get('map');
  const first = maps.find((m) => m.map === wanted) || maps.find((m) => m.map === 'demo') || maps[0];
  if (!first) {
    setStatus('no maps yet: create one and stream scans into it');
    window.__viewerReady = true;
    return;
  }
  picker.value = first.map;
  picker.onchange = async () => {
    const all = await listMaps();
    await openMap(picker.value, all.find((m) => m.map === picker.value)).catch(fail);
  };
  ui.scene.onRender = () => {
    if (ui.model && !window.__viewerReady && ui.scene.drawnCount() > 0) {
      window.__viewerReady = true;
      publish();
    }
  };
  await openMap(first.map, first);
  if (ui.flat.n === 0) window.__viewerReady = true;
}

// ---------------------------------------------------------------------------------------------
// Tools: inspect (click a cell), box, ray

function showInfo(html) {
  $('info').innerHTML = html;
}

async function inspect(x, y) {
  const pick = ui.scene.pickCell(x, y);
  if (!pick) return;
  const f = ui.flat;
  const i = pick.index;
  const centre = Array.from(f.centres.subarray(3 * i, 3 * i + 3));
  const size = f.sizes[i];
  const coarse = size > ui.model.store.resolution * 1.01;
  const client = { probability: f.probability[i], variance: f.variance[i], state: STATE_NAMES[ui.classes[i]] };
  const c = coarse ? null : await cellAt(ui.model.name, centre, ui.thresholds);
  const shown = c || client;
  ui.info = { centre, size, coarse, client, server: c };
  const el = $('info');
  el.dataset.probability = shown.probability;
  el.dataset.variance = shown.variance;
  el.dataset.state = shown.state;
  el.dataset.clientState = client.state;
  el.dataset.centre = centre.join(',');
  showInfo(
    `<b>${coarse ? `cube of ${Math.round(size / ui.model.store.resolution)}³ cells` : `cell ${c.cell.join(', ')}`}</b>` +
      `<div>centre ${centre.map((v) => v.toFixed(2)).join(', ')} m</div>` +
      `<div>probability <span id="info-p">${shown.probability.toFixed(4)}</span></div>` +
      `<div>variance <span id="info-var">${shown.variance.toExponential(3)}</span></div>` +
      `<div>state <span id="info-state">${shown.state}</span></div>` +
      (c ? `<div>evidence α ${c.alpha.toFixed(3)}, β ${c.beta.toFixed(3)}</div>` : ''),
  );
  publish();
}

function zRange() {
  const e = ui.model.extent;
  return [e.min[2], e.max[2] - 1e-3];
}

async function boxTool(x, y) {
  const [z0, z1] = zRange();
  const p = ui.scene.pointOnPlane(x, y, z0);
  if (!p) return;
  ui.clicks.push(p);
  if (ui.clicks.length < 2) return setStatus('box: click the opposite corner');
  const [a, b] = ui.clicks;
  const min = [Math.min(a[0], b[0]), Math.min(a[1], b[1]), z0];
  const max = [Math.max(a[0], b[0]), Math.max(a[1], b[1]), z1];
  endTool();
  const r = await boxCounts(ui.model.name, min, max, ui.thresholds);
  ui.scene.showBox(min, max);
  ui.box = { min, max, counts: r.counts, version: r.version };
  const el = $('info');
  el.dataset.box = JSON.stringify(ui.box);
  showInfo(
    `<b>box query</b><div>${min.map((v) => v.toFixed(2)).join(', ')} → ${max.map((v) => v.toFixed(2)).join(', ')}</div>` +
      `<div id="box-counts">${r.counts.occupied} occupied · ${r.counts.free} free · ${r.counts.unknown} unknown</div>`,
  );
  publish();
}

async function rayTool(x, y) {
  const z = Number($('ray-z').value);
  const p = ui.scene.pointOnPlane(x, y, z);
  if (!p) return;
  ui.clicks.push(p);
  if (ui.clicks.length < 2) return setStatus('ray: click where the ray should end');
  const [from, to] = ui.clicks;
  endTool();
  const d = to.map((v, k) => v - from[k]);
  const range = Math.hypot(...d);
  if (range === 0) return;
  const r = (await castRay(ui.model.name, from, d, range, ui.thresholds)).results[0];
  const hit = r.blocked ? from.map((v, k) => v + (d[k] / range) * r.distance) : null;
  ui.scene.showRay(from, to, hit);
  ui.ray = { from, to, result: r };
  showInfo(
    `<b>ray query</b><div id="ray-result">${r.blocked ? `blocked at ${r.distance.toFixed(2)} m (${r.state}, p ${r.probability.toFixed(3)})` : `clear for ${range.toFixed(2)} m`}</div>`,
  );
  publish();
}

function startTool(tool) {
  ui.tool = tool;
  ui.clicks = [];
  for (const b of document.querySelectorAll('[data-tool]')) b.classList.toggle('active', b.dataset.tool === tool);
  setStatus(tool === 'box' ? 'box: click a corner on the floor' : tool === 'ray' ? 'ray: click the start' : 'live');
}

function endTool() {
  startTool('inspect');
}

function onClick(x, y) {
  if (!ui.model) return;
  const run = ui.tool === 'box' ? boxTool : ui.tool === 'ray' ? rayTool : inspect;
  run(x, y).catch(fail);
}

// ---------------------------------------------------------------------------------------------
// Test hooks

function publish() {
  const m = ui.model;
  window.__viewer = {
    ready: Boolean(window.__viewerReady),
    map: m && m.name,
    version: m ? m.version : 0,
    large: Boolean(m && m.large),
    coarsen: m ? m.store.coarsen : 0,
    extent: m && m.extent,
    detail: Boolean(m && m.detail),
    cells: ui.flat ? ui.flat.n : 0,
    drawn: ui.scene.drawnCount(),
    counts: { free: ui.counts[FREE], occupied: ui.counts[OCCUPIED], unknown: ui.counts[UNKNOWN] },
    thresholds: { ...ui.thresholds },
    poses: m ? m.poses.length : 0,
    updates: m ? m.updates : 0,
    info: ui.info,
    box: ui.box,
    ray: ui.ray,
    status: ui.status,
    errors: ui.errors.slice(),
    // Milliseconds of the last redraw's JavaScript and of the last WebGL frame.
    timing: { draw: ui.drawMs || 0, render: ui.scene.renderMs || 0 },
    // Page coordinates of a world point, and the centre of an occupied cell near the view's
    // centre, so a test can click real pixels.
    project: (p) => ui.scene.project(p),
    occupiedCentre: () => nearestOccupiedToTarget(),
    occupiedWithin: (min, max) => countOccupiedWithin(min, max),
  };
}

function countOccupiedWithin(min, max) {
  const f = ui.flat;
  let n = 0;
  for (let i = 0; f && i < f.n; i++) {
    const c = f.centres.subarray(3 * i, 3 * i + 3);
    if (ui.classes[i] === OCCUPIED && [0, 1, 2].every((k) => c[k] >= min[k] && c[k] <= max[k])) n++;
  }
  return n;
}

function nearestOccupiedToTarget() {
  const f = ui.flat;
  const t = ui.scene.target();
  let best = -1;
  let bestD = Infinity;
  for (let i = 0; f && i < f.n; i++) {
    if (ui.classes[i] !== OCCUPIED) continue;
    const d = Math.hypot(f.centres[3 * i] - t[0], f.centres[3 * i + 1] - t[1], f.centres[3 * i + 2] - t[2]);
    if (d < bestD) [best, bestD] = [i, d];
  }
  return best < 0 ? null : Array.from(f.centres.subarray(3 * best, 3 * best + 3));
}

// ---------------------------------------------------------------------------------------------
// Wiring

for (const id of ['p-free', 'p-occ', 'var-max']) {
  $(id).addEventListener('input', () => {
    readThresholds();
    draw();
  });
}
for (const id of ['colour', 'show-free', 'show-unknown']) $(id).addEventListener('change', draw);
for (const b of document.querySelectorAll('[data-tool]')) b.addEventListener('click', () => startTool(b.dataset.tool));
$('clear').addEventListener('click', () => {
  ui.scene.clearMarkers();
  ui.box = ui.ray = ui.info = null;
  showInfo('');
  publish();
});

let down = null;
const canvas = $('view');
canvas.addEventListener('pointerdown', (e) => (down = { x: e.clientX, y: e.clientY, t: performance.now() }));
canvas.addEventListener('pointerup', (e) => {
  if (down && Math.hypot(e.clientX - down.x, e.clientY - down.y) < 5 && performance.now() - down.t < 600) {
    onClick(e.clientX, e.clientY);
  }
  down = null;
});
ui.scene.controls.addEventListener('end', () => {
  if (ui.model && ui.model.large) ui.model.refine(ui.scene.target()).catch(fail);
});

start().catch(fail);
