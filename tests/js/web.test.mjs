// The web page at / in headless Chromium (Debian's chromium, driven by
// playwright-core), against the real server on a loopback port (issue 8).
// Screenshots go to ITEAS_TEST_OUTPUT (default: build/test-output).
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import fs from 'node:fs';
import path from 'node:path';
import { chromium } from 'playwright-core';
import { DATA, SOURCE_DIR, startServer, stopServer, killLeftoverServers } from './check.mjs';

const CHROMIUM = process.env.CHROMIUM || '/usr/bin/chromium';
const OUT = process.env.ITEAS_TEST_OUTPUT || path.join(SOURCE_DIR, 'build/test-output');
fs.mkdirSync(OUT, { recursive: true });

let browser;
before(async () => {
  browser = await chromium.launch({
    executablePath: CHROMIUM,
    args: ['--headless', '--no-sandbox', '--disable-gpu', '--disable-quic', '--no-first-run',
      '--disable-background-networking', '--disable-component-update', '--disable-sync',
      '--use-angle=swiftshader', '--enable-unsafe-swiftshader'],
  });
});
after(async () => { if (browser) await browser.close(); killLeftoverServers(); });

async function openPage(url) {
  const page = await browser.newPage({ viewport: { width: 1280, height: 1000 } });
  const problems = [];
  page.on('pageerror', (e) => problems.push(`page error: ${e.message}`));
  page.on('requestfailed', (r) => problems.push(`request failed: ${r.url()}`));
  page.on('console', (m) => { if (m.type() === 'error') problems.push(`console: ${m.text()}`); });
  // Only the server on loopback: anything else would mean a CDN.
  await page.route('**/*', (route) => (route.request().url().startsWith(url) ? route.continue() : route.abort()));
  await page.goto(url + '/');
  await page.waitForFunction(() => document.body.dataset.state === 'idle', null, { timeout: 20000 });
  return { page, problems };
}

// Share of pixels of a view's WebGL canvas that are not the white background.
async function inkShare(page, selector) {
  return page.evaluate((sel) => {
    const gl = document.querySelector(sel);
    const c = document.createElement('canvas');
    c.width = gl.width; c.height = gl.height;
    const ctx = c.getContext('2d');
    ctx.drawImage(gl, 0, 0);
    const d = ctx.getImageData(0, 0, c.width, c.height).data;
    let ink = 0;
    for (let i = 0; i < d.length; i += 4) if (d[i] < 240 || d[i + 1] < 240 || d[i + 2] < 240) ++ink;
    return ink / (d.length / 4);
  }, selector);
}

const cell = (page, key) => page.locator(`#summary-table td[data-key="${key}"]`).innerText();
const number = (text) => Number(text.replace(/,/g, ''));

test('upload, refine through the job API, both views render, the table matches the API', async () => {
  const s = await startServer(['--workers', '2']);
  try {
    const { page, problems } = await openPage(s.url);
    const mesh = path.join(DATA, 'bunny-npm.obj');
    await page.setInputFiles('#file', mesh);
    await page.waitForFunction(() => /triangles/.test(document.getElementById('in-count').textContent), null, { timeout: 20000 });
    await page.fill('input[name=levels]', '3');
    await page.click('#run');
    await page.waitForFunction(() => ['done', 'error'].includes(document.body.dataset.state), null, { timeout: 120000 });
    assert.equal(await page.evaluate(() => document.body.dataset.state), 'done', await page.locator('#error').innerText());
    await page.screenshot({ path: path.join(OUT, 'web-bunny.png'), fullPage: true });

    const inInk = await inkShare(page, '#view-in canvas'), outInk = await inkShare(page, '#view-out canvas');
    assert.ok(inInk > 0.02, `input view is blank (${inInk})`);
    assert.ok(outInk > 0.02, `output view is blank (${outInk})`);
    assert.ok(await inkShare(page, '#chart') > 0.01, 'the chart is blank');

    // The same request through the API directly.
    const api = await fetch(`${s.url}/v1/refine?levels=3`, { method: 'POST', headers: { 'Content-Type': 'model/obj' }, body: fs.readFileSync(mesh) });
    assert.equal(api.status, 200);
    const stats = JSON.parse(api.headers.get('x-iteas-stats'));
    assert.equal(number(await cell(page, 'input triangles')), stats.input.triangles);
    assert.equal(number(await cell(page, 'output triangles')), stats.output.triangles);
    const rows = await page.locator('#levels-table tbody tr').count();
    assert.equal(rows, stats.levels.length);
    for (let i = 0; i < rows; ++i) {
      const after = await page.locator(`#levels-table tbody tr:nth-child(${i + 1}) td:nth-child(7)`).innerText();
      assert.equal(number(after), stats.levels[i].triangles_after, `level ${i + 1}`);
    }
    // What the browser decoded from the downloaded GLB has those triangles too.
    const result = await page.evaluate(() => window.iteasResult);
    assert.equal(result.outputTriangles, stats.output.triangles);
    assert.equal(result.inputTriangles, stats.input.triangles);
    assert.ok(await page.locator('#download').isVisible());
    // Wireframe and level colours toggle without errors and still draw.
    await page.check('#wireframe');
    assert.ok(await inkShare(page, '#view-out canvas') > 0.005);
    assert.deepEqual(problems, []);
    await page.close();
  } finally {
    await stopServer(s);
  }
});

test('a bad file shows the error envelope\'s message, not a blank page', async () => {
  const s = await startServer();
  try {
    const { page } = await openPage(s.url);
    const bad = path.join(DATA, 'nasty', 'test_lines.obj');
    const api = await fetch(`${s.url}/v1/jobs`, { method: 'POST', headers: { 'Content-Type': 'model/obj' }, body: fs.readFileSync(bad) });
    let expected;
    if (api.status === 202) {
      const { id } = await api.json();
      for (;;) {
        const st = await (await fetch(`${s.url}/v1/jobs/${id}`)).json();
        if (st.status === 'failed') { expected = st.error.message; break; }
        assert.ok(['queued', 'running'].includes(st.status), `a lines-only OBJ ended ${st.status}`);
        await new Promise((r) => setTimeout(r, 100));
      }
    } else {
      expected = (await api.json()).error.message;
    }
    await page.setInputFiles('#file', bad);
    await page.click('#run');
    await page.waitForFunction(() => document.body.dataset.state === 'error', null, { timeout: 60000 });
    const shown = await page.locator('#error').innerText();
    assert.ok(shown.includes(expected), `page shows "${shown}", the API says "${expected}"`);
    assert.ok(await page.locator('header h1').isVisible(), 'the page is still there');
    await page.screenshot({ path: path.join(OUT, 'web-error.png') });
    await page.close();
  } finally {
    await stopServer(s);
  }
});

test('with an API key the page works when the key is given and shows 401 when not', async () => {
  const s = await startServer(['--api-key', 'page-secret']);
  try {
    const { page } = await openPage(s.url);
    await page.setInputFiles('#file', path.join(DATA, 'eight.off'));
    await page.fill('input[name=levels]', '1');
    await page.click('#run');
    await page.waitForFunction(() => document.body.dataset.state === 'error', null, { timeout: 60000 });
    assert.match(await page.locator('#error').innerText(), /unauthorized|Authorization/);
    await page.fill('#api-key', 'page-secret');
    await page.click('#run');
    await page.waitForFunction(() => document.body.dataset.state === 'done', null, { timeout: 60000 });
    assert.ok(await page.locator('#error').isHidden());
    await page.close();
  } finally {
    await stopServer(s);
  }
});
