// Takes the README's screenshot of the viewer: starts the real `bgkmap demo` (BGKMAP_BIN, or
// the debug build) on free ports, opens the viewer in Debian's chromium, saves a PNG.
//
//   node tests/browser/screenshot.mjs OUT.png   (after `npm ci` in tests/browser)

import { writeFileSync } from 'node:fs';
import { chromium } from 'playwright-core';
import { startDemo } from './demo.mjs';

const out = process.argv[2];
if (!out) {
  console.error('usage: node tests/browser/screenshot.mjs OUT.png');
  process.exit(2);
}
const demo = await startDemo();
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || '/usr/bin/chromium',
  headless: true,
  args: ['--no-sandbox', '--disable-gpu', '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
});
try {
  const page = await browser.newPage({ viewport: { width: 960, height: 600 } });
  await page.goto(`http://${demo.http}/`);
  await page.waitForFunction(() => window.__viewerReady === true, null, { timeout: 120_000 });
  await page.waitForTimeout(1000);
  writeFileSync(out, await page.screenshot());
  console.log(`wrote ${out}`);
} finally {
  await browser.close();
  await demo.stop();
}
