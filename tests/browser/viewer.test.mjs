// The web viewer in a real browser (Debian's chromium driven by playwright-core) against the
// real `bgkmap demo`: cells drawn and visible, a clicked cell's numbers equal the server's,
// the box and ray tools run real queries, client-side thresholds classify exactly as the
// server, a newly streamed scan appears, a large map is drawn coarse and refined — with no
// console errors and no request to anything but the server.

import { after, before, describe, test } from 'node:test';
import assert from 'node:assert/strict';
import { mkdirSync, writeFileSync } from 'node:fs';
import { chromium } from 'playwright-core';
import { startDemo } from './demo.mjs';
import { countForeground, decodePng } from './png.mjs';

const CHROMIUM = process.env.CHROMIUM || '/usr/bin/chromium';
const ARTIFACTS = process.env.BGKMAP_ARTIFACTS || new URL('./artifacts/', import.meta.url).pathname;
const BACKGROUND = [0xf3, 0xf4, 0xf6];

let demo;
let browser;

before(async () => {
  demo = await startDemo(['--scans', '8']);
  browser = await chromium.launch({
    executablePath: CHROMIUM,
    headless: true,
    args: ['--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run', '--disable-background-networking',
      '--disable-component-update', '--disable-sync', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
});

after(async () => {
  if (browser) await browser.close();
  if (demo) await demo.stop();
});

// A page on the viewer that records console errors, page errors and every request.
async function openViewer(query = '') {
  const page = await browser.newPage({ viewport: { width: 1100, height: 700 } });
  const seen = { errors: [], requests: [] };
  page.on('console', (m) => m.type() === 'error' && seen.errors.push(m.text()));
  page.on('pageerror', (e) => seen.errors.push(String(e)));
  page.on('request', (r) => seen.requests.push(r.url()));
  await page.goto(`http://${demo.http}/${query}`);
  await page.waitForFunction(() => window.__viewerReady === true, null, { timeout: 120_000 });
  return { page, seen };
}

const viewer = (page) => page.evaluate(() => JSON.parse(JSON.stringify(window.__viewer)));

async function postJson(path, body) {
  const r = await fetch(`http://${demo.http}${path}`, { method: 'POST', body: JSON.stringify(body) });
  const json = await r.json();
  assert.equal(r.status, 200, JSON.stringify(json));
  return json;
}

function assertClean(seen) {
  assert.deepEqual(seen.errors, [], 'no console or page errors');
  const origin = `http://${demo.http}/`;
  const foreign = seen.requests.filter((u) => !u.startsWith(origin) && !u.startsWith('data:'));
  assert.deepEqual(foreign, [], 'no request beyond the server');
}

// Sets a range input as a person dragging it would (an `input` event).
async function setSlider(page, id, value) {
  await page.evaluate(([id, value]) => {
    const el = document.getElementById(id);
    el.value = String(value);
    el.dispatchEvent(new Event('input', { bubbles: true }));
  }, [id, value]);
}

async function clickWorld(page, p) {
  const at = await page.evaluate((p) => window.__viewer.project(p), p);
  assert.ok(at.visible, `world point ${p} is in view`);
  await page.mouse.click(at.x, at.y);
}

describe('the viewer on the demo map', () => {
  let page;
  let seen;

  before(async () => {
    ({ page, seen } = await openViewer());
  });

  after(async () => {
    if (page) await page.close();
  });

  test('draws the cells: the screenshot shows them', async () => {
    const v = await viewer(page);
    const info = await (await fetch(`http://${demo.http}/v1/maps/demo`)).json();
    assert.equal(v.map, 'demo');
    assert.equal(v.version, info.version);
    assert.equal(v.cells, info.cells_with_evidence, 'every cell with evidence arrived');
    assert.ok(v.drawn > 1000 && v.drawn === v.counts.occupied, `${v.drawn} occupied cells drawn`);
    assert.equal(v.poses, 8, 'one sensor frame per scan');
    const shot = await page.screenshot();
    mkdirSync(ARTIFACTS, { recursive: true });
    writeFileSync(`${ARTIFACTS}/viewer.png`, shot);
    const img = decodePng(shot);
    const box = await page.locator('#view').boundingBox();
    const rect = { x: Math.ceil(box.x), y: Math.ceil(box.y), width: Math.floor(box.width), height: Math.floor(box.height) };
    const fg = countForeground(img, rect, BACKGROUND);
    // The room fills a good part of the view, in many shades (lit faces × height colours).
    assert.ok(fg.count > 0.1 * fg.total, `${fg.count} of ${fg.total} canvas pixels differ from the background`);
    assert.ok(fg.colours > 100, `${fg.colours} distinct colours`);
  });

  test('thresholds re-classify on the client exactly as the server does', async () => {
    const v0 = await viewer(page);
    const { min, max } = v0.extent;
    const box = { min, max: max.map((x) => x - 1e-3) };
    const server = async (thresholds) => (await postJson('/v1/maps/demo/query/box', { ...box, counts_only: true, thresholds })).counts;
    assert.deepEqual(v0.counts, await server(v0.thresholds));
    await setSlider(page, 'p-occ', 0.9);
    await setSlider(page, 'p-free', 0.15);
    await setSlider(page, 'var-max', 2); // 0.005
    const v1 = await viewer(page);
    assert.deepEqual(v1.thresholds, { p_free: 0.15, p_occ: 0.9, var_max: 0.005 });
    assert.deepEqual(v1.counts, await server(v1.thresholds));
    assert.ok(v1.counts.occupied < v0.counts.occupied, 'a stricter p_occ leaves fewer occupied cells');
    assert.equal(v1.drawn, v1.counts.occupied);
    await page.check('#show-unknown');
    assert.equal((await viewer(page)).drawn, v1.counts.occupied + v1.counts.unknown);
    await page.uncheck('#show-unknown');
    await setSlider(page, 'p-occ', 0.7);
    await setSlider(page, 'p-free', 0.3);
    await setSlider(page, 'var-max', 100);
    assert.deepEqual((await viewer(page)).counts, v0.counts);
  });

  test('clicking a cell shows the server\'s probability, variance and state', async () => {
    const centre = await page.evaluate(() => window.__viewer.occupiedCentre());
    await clickWorld(page, centre);
    await page.waitForFunction(() => window.__viewer.info && window.__viewer.info.server);
    const { info } = await viewer(page);
    const panel = await page.locator('#info').evaluate((el) => ({ ...el.dataset, text: el.innerText }));
    const at = info.centre.join(',');
    const cell = await (await fetch(`http://${demo.http}/v1/maps/demo/cell?at=${at}`)).json();
    assert.equal(Number(panel.probability), cell.probability);
    assert.equal(Number(panel.variance), cell.variance);
    assert.equal(panel.state, cell.state);
    assert.equal(panel.clientState, cell.state, 'the client classifies the clicked cell as the server');
    assert.equal(await page.locator('#info-state').innerText(), cell.state);
    assert.equal(await page.locator('#info-p').innerText(), cell.probability.toFixed(4));
    assert.match(panel.text, /evidence α [\d.]+, β [\d.]+/);
    // And the same numbers come from the plain point query.
    const point = (await postJson('/v1/maps/demo/query/points', { points: [info.centre] })).results[0];
    assert.deepEqual([point.probability, point.variance, point.state], [cell.probability, cell.variance, cell.state]);
  });

  test('the box tool runs a box query', async () => {
    const { extent } = await viewer(page);
    const c = [0, 1].map((k) => (extent.min[k] + extent.max[k]) / 2);
    await page.click('[data-tool=box]');
    await clickWorld(page, [c[0] - 1.5, c[1] - 1, extent.min[2]]);
    await clickWorld(page, [c[0] + 1, c[1] + 1.5, extent.min[2]]);
    await page.waitForFunction(() => window.__viewer.box);
    const { box, thresholds } = await viewer(page);
    assert.ok(Math.abs(box.min[0] - (c[0] - 1.5)) < 0.05 && Math.abs(box.max[1] - (c[1] + 1.5)) < 0.05, JSON.stringify(box));
    const server = await postJson('/v1/maps/demo/query/box', { min: box.min, max: box.max, counts_only: true, thresholds });
    assert.deepEqual(box.counts, server.counts);
    assert.ok(server.counts.occupied > 0 && server.counts.free > 0);
    const text = await page.locator('#box-counts').innerText();
    assert.equal(text, `${server.counts.occupied} occupied · ${server.counts.free} free · ${server.counts.unknown} unknown`);
  });

  test('the ray tool runs a ray query', async () => {
    const { extent } = await viewer(page);
    const c = [0, 1].map((k) => (extent.min[k] + extent.max[k]) / 2);
    await page.click('[data-tool=ray]');
    await clickWorld(page, [c[0], c[1], 1.0]);
    await clickWorld(page, [extent.max[0] + 0.5, c[1], 1.0]);
    await page.waitForFunction(() => window.__viewer.ray);
    const { ray } = await viewer(page);
    const d = ray.to.map((v, k) => v - ray.from[k]);
    const server = await postJson('/v1/maps/demo/query/rays', { rays: [{ origin: ray.from, direction: d, max_range: Math.hypot(...d) }] });
    assert.deepEqual(ray.result, server.results[0]);
    assert.ok(['clear', 'blocked'].includes(ray.result.verdict));
  });

  test('a newly streamed scan appears', async () => {
    const v0 = await viewer(page);
    const { min, max } = v0.extent;
    const c = [0, 1].map((k) => (min[k] + max[k]) / 2);
    // A 1.2 m square of returns above the walls, seen from above: cells no scan has touched.
    const z = max[2] + 0.6;
    const points = [];
    for (let i = 0; i < 24; i++) for (let j = 0; j < 24; j++) points.push([c[0] - 0.6 + i * 0.05, c[1] - 0.6 + j * 0.05, z]);
    const patchMin = [c[0] - 0.7, c[1] - 0.7, z - 0.3];
    const patchMax = [c[0] + 0.7, c[1] + 0.7, z + 0.3];
    assert.equal(await page.evaluate(([a, b]) => window.__viewer.occupiedWithin(a, b), [patchMin, patchMax]), 0);
    const sent = performance.now();
    const ack = await postJson('/v1/maps/demo/scans?wait_applied=true', {
      source: 'browser-test', seq: 1, pose: { translation: [c[0], c[1], z + 2], rotation: [1, 0, 0, 0] }, points,
    });
    assert.equal(ack.version, v0.version + 1);
    await page.waitForFunction((v) => window.__viewer.version === v, ack.version, { timeout: 30_000 });
    const ms = performance.now() - sent;
    const v1 = await viewer(page);
    const appeared = await page.evaluate(([a, b]) => window.__viewer.occupiedWithin(a, b), [patchMin, patchMax]);
    assert.ok(appeared > 50, `${appeared} occupied cells appeared where the scan hit`);
    assert.equal(v1.poses, v0.poses + 1, 'its sensor pose is drawn');
    const info = await (await fetch(`http://${demo.http}/v1/maps/demo`)).json();
    assert.equal(v1.cells, info.cells_with_evidence, 'the patched map holds exactly the server\'s cells');
    console.log(`# the scan was on screen ${ms.toFixed(0)} ms after it was sent`);
    assertClean(seen);
  });
});

test('a large map is drawn coarse and refined near the camera', async () => {
  const { page, seen } = await openViewer('?large=1000&refine=1.5');
  try {
    const v = await viewer(page);
    assert.ok(v.large && v.detail, 'treated as large, with a refined region');
    assert.ok(v.coarsen >= 2, `overview coarsened (level ${v.coarsen})`);
    const info = await (await fetch(`http://${demo.http}/v1/maps/demo`)).json();
    assert.ok(v.cells < info.cells_with_evidence / 2, `${v.cells} drawn items for ${info.cells_with_evidence} cells`);
    assert.ok(v.drawn > 500);
    const cells = seen.requests.filter((u) => u.includes('/cells?'));
    assert.ok(cells.some((u) => /coarsen=2/.test(u)), cells.join('\n'));
    assert.ok(cells.some((u) => /min=.*max=/.test(u) && !/coarsen/.test(u)), cells.join('\n'));
    assertClean(seen);
  } finally {
    await page.close();
  }
});
