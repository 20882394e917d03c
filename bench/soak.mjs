// Soak test of `iteas serve` on loopback (hardening issue, point 4): good, bad
// and cancelled requests from many connections for a bounded time, with the
// server's RSS, open file descriptors and thread count sampled every few
// seconds. Writes the samples as CSV and a Markdown summary; exit 1 on a crash,
// a 5xx, or growth after warm-up.
//   node bench/soak.mjs [seconds=600] [connections=24] [out-dir=docs/soak]
import { spawn } from 'node:child_process';
import fs from 'node:fs';
import path from 'node:path';

const SRC = path.resolve(path.dirname(new URL(import.meta.url).pathname), '..');
const BIN = process.env.ITEAS_BIN || path.join(SRC, 'build/iteas');
const DATA = path.join(SRC, 'tests/data');
const seconds = Number(process.argv[2] || 600);
const connections = Number(process.argv[3] || 24);
const outDir = path.resolve(process.argv[4] || path.join(SRC, 'docs/soak'));
const SAMPLE_MS = 5000;

const good = [
  ['Box.glb', 'model/gltf-binary', ''], ['eight.off', 'application/octet-stream', ''],
  ['bunny-npm.obj', 'model/obj', 'levels=3'], ['Avocado.notex.draco.glb', 'model/gltf-binary', ''],
  ['decimated-knight.off', 'application/octet-stream', 'mode=uniform&levels=2'],
  ['cube_att.drc', 'application/octet-stream', 'mode=fixed&threshold=10&levels=2'],
].map(([f, type, q]) => ({ file: f, type, query: q, body: fs.readFileSync(path.join(DATA, f)) }));
const nasty = fs.readdirSync(path.join(DATA, 'nasty')).filter((f) => !f.endsWith('.md'))
  .map((f) => ({ file: `nasty/${f}`, type: 'application/octet-stream', query: '', body: fs.readFileSync(path.join(DATA, 'nasty', f)) }));
const bad = [
  ...nasty,
  { file: 'garbage', type: 'application/octet-stream', query: '', body: Buffer.from('this is not a mesh at all') },
  { file: 'truncated Box.glb', type: 'model/gltf-binary', query: '', body: fs.readFileSync(path.join(DATA, 'Box.glb')).subarray(0, 300) },
  { file: 'bad option', type: 'model/gltf-binary', query: 'levels=99', body: fs.readFileSync(path.join(DATA, 'Box.glb')) },
  { file: 'bad media type', type: 'text/html', query: '', body: Buffer.from('<html></html>') },
];

const proc = spawn(BIN, ['serve', '--port', '0', '--workers', '2', '--queue', '64'], { stdio: ['ignore', 'pipe', 'pipe'] });
let log = '';
let exited = null;
proc.on('exit', (code, signal) => { exited = code ?? signal; });
const port = await new Promise((resolve, reject) => {
  const timer = setTimeout(() => reject(new Error('server did not start')), 10000);
  proc.stdout.on('data', (d) => {
    log += d;
    const m = log.match(/listening on [^:]+:(\d+)/);
    if (m) { clearTimeout(timer); resolve(Number(m[1])); }
  });
});
proc.stdout.on('data', () => {});  // keep the pipe drained
proc.stderr.on('data', () => {});
const url = `http://127.0.0.1:${port}`;

const counts = { good: 0, bad_4xx: 0, cancelled: 0, aborted: 0, busy_429: 0, server_5xx: 0, unexpected: 0 };
const unexpected = [];
const note = (what) => { counts.unexpected++; if (unexpected.length < 20) unexpected.push(what); };

async function goodRequest(p) {
  const r = await fetch(`${url}/v1/refine?${p.query}`, { method: 'POST', headers: { 'Content-Type': p.type }, body: p.body });
  await r.arrayBuffer();
  if (r.status === 200) counts.good++;
  else if (r.status === 429) counts.busy_429++;
  else if (r.status >= 500) { counts.server_5xx++; note(`${p.file}: ${r.status}`); } else note(`${p.file}: ${r.status}`);
}
async function badRequest(p) {
  const r = await fetch(`${url}/v1/refine?${p.query}`, { method: 'POST', headers: { 'Content-Type': p.type }, body: p.body });
  await r.arrayBuffer();
  if (r.status >= 500) { counts.server_5xx++; note(`${p.file}: ${r.status}`); } else if (r.status >= 400) counts.bad_4xx++;
  else if (r.status === 200) counts.good++;  // some broken files are repaired with warnings
}
async function cancelledJob(p) {
  const r = await fetch(`${url}/v1/jobs?mode=uniform&levels=5`, { method: 'POST', headers: { 'Content-Type': p.type }, body: p.body });
  if (r.status === 429) { counts.busy_429++; await r.arrayBuffer(); return; }
  if (r.status !== 202) { if (r.status >= 500) counts.server_5xx++; note(`job submit ${r.status}`); await r.arrayBuffer(); return; }
  const { id } = await r.json();
  await new Promise((resolve) => setTimeout(resolve, Math.random() * 50));
  const d = await fetch(`${url}/v1/jobs/${id}`, { method: 'DELETE' });
  await d.arrayBuffer();
  if (d.status === 200 || d.status === 404) counts.cancelled++;
  else { if (d.status >= 500) counts.server_5xx++; note(`delete ${d.status}`); }
}
async function abortedRequest(p) {
  const ac = new AbortController();
  setTimeout(() => ac.abort(), 5 + Math.random() * 40);
  try {
    const r = await fetch(`${url}/v1/refine?mode=uniform&levels=4`, { method: 'POST', headers: { 'Content-Type': p.type }, body: p.body, signal: ac.signal });
    await r.arrayBuffer();
    if (r.status >= 500) { counts.server_5xx++; note(`aborted ${r.status}`); }
  } catch { /* the client gave up: that is the point */ }
  counts.aborted++;
}

const deadline = Date.now() + seconds * 1000;
async function client(k) {
  let i = k;
  while (Date.now() < deadline && exited === null) {
    const kind = process.env.SOAK_KIND ? Number(process.env.SOAK_KIND) : i % 10;
    try {
      if (kind < 5) await goodRequest(good[i % good.length]);
      else if (kind < 8) await badRequest(bad[i % bad.length]);
      else if (kind === 8) await cancelledJob(good[i % good.length]);
      else await abortedRequest(good[2]);
    } catch (e) {
      if (exited !== null) break;
      note(`client error: ${e.message}`);
    }
    ++i;
  }
}

function sample(t0) {
  const status = fs.readFileSync(`/proc/${proc.pid}/status`, 'utf8');
  return {
    t: Math.round((Date.now() - t0) / 1000),
    rss_mib: Number(status.match(/VmRSS:\s+(\d+)/)[1]) / 1024,
    threads: Number(status.match(/Threads:\s+(\d+)/)[1]),
    fds: fs.readdirSync(`/proc/${proc.pid}/fd`).length,
  };
}

const t0 = Date.now();
const samples = [sample(t0)];
const timer = setInterval(() => { if (exited === null) samples.push(sample(t0)); }, SAMPLE_MS);
await Promise.all(Array.from({ length: connections }, (_, k) => client(k)));
clearInterval(timer);
if (exited === null) samples.push(sample(t0));
const crashed = exited !== null;
const stop = new Promise((resolve) => proc.on('exit', (code, signal) => resolve(code ?? signal)));
if (!crashed) proc.kill('SIGTERM');
const exitCode = crashed ? exited : await stop;

// Flat after warm-up: the last third against the second third (max values).
const warm = samples.filter((s) => s.t >= seconds / 3);
const mid = warm.filter((s) => s.t < (2 * seconds) / 3), late = warm.filter((s) => s.t >= (2 * seconds) / 3);
const max = (arr, k) => Math.max(...arr.map((s) => s[k]));
const growth = (k) => (mid.length && late.length ? max(late, k) - max(mid, k) : 0);
const flat = growth('rss_mib') <= Math.max(32, 0.1 * max(mid, 'rss_mib')) && growth('fds') <= 4 && growth('threads') <= 4;

fs.mkdirSync(outDir, { recursive: true });
fs.writeFileSync(path.join(outDir, 'samples.csv'), 't_s,rss_mib,fds,threads\n' + samples.map((s) => `${s.t},${s.rss_mib.toFixed(1)},${s.fds},${s.threads}`).join('\n') + '\n');
const summary = `# Soak: ${seconds} s, ${connections} connections (${new Date().toISOString().slice(0, 10)})

Command: \`node bench/soak.mjs ${seconds} ${connections}\` (the server on loopback, 2 workers).
Mix per client: 50 % good refines (6 meshes), 30 % bad requests (every file of tests/data/nasty,
garbage, a truncated GLB, a bad option, a wrong media type), 10 % jobs cancelled by DELETE right
after submission, 10 % synchronous refines the client aborts after 5-45 ms.

| outcome | count |
|---|---:|
${Object.entries(counts).map(([k, v]) => `| ${k} | ${v} |`).join('\n')}
| server exit | ${crashed ? `crashed (${exited})` : `SIGTERM drain, exit ${exitCode}`} |

| sampled every ${SAMPLE_MS / 1000} s | start | max 2nd third | max last third | end |
|---|---:|---:|---:|---:|
| RSS MiB | ${samples[0].rss_mib.toFixed(1)} | ${max(mid, 'rss_mib').toFixed(1)} | ${max(late, 'rss_mib').toFixed(1)} | ${samples.at(-1).rss_mib.toFixed(1)} |
| open fds | ${samples[0].fds} | ${max(mid, 'fds')} | ${max(late, 'fds')} | ${samples.at(-1).fds} |
| threads | ${samples[0].threads} | ${max(mid, 'threads')} | ${max(late, 'threads')} | ${samples.at(-1).threads} |

Flat after warm-up: **${flat ? 'yes' : 'no'}**. All ${samples.length} samples: [samples.csv](samples.csv).
${unexpected.length ? '\nUnexpected answers:\n' + unexpected.map((u) => `- ${u}`).join('\n') + '\n' : ''}`;
fs.writeFileSync(path.join(outDir, 'README.md'), summary);
console.log(summary);
process.exit(!crashed && exitCode === 0 && counts.server_5xx === 0 && counts.unexpected === 0 && flat ? 0 : 1);
