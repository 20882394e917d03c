// Load benchmark of `iteas serve` on loopback (issue 4, point 5). Bounded in
// time; every request goes to 127.0.0.1.
//   node bench/load.mjs [seconds=60] [connections=32]
// Prints requests/s, p50/p99 latency, failures, the server's resident memory
// over time, and the server's time per job against the CLI's on the same
// ~100k-triangle job (eight.off, uniform, 3 levels: 98,304 triangles).
import { spawn, spawnSync } from 'node:child_process';
import fs from 'node:fs';
import path from 'node:path';
import os from 'node:os';

const SRC = path.resolve(path.dirname(new URL(import.meta.url).pathname), '..');
const BIN = process.env.ITEAS_BIN || path.join(SRC, 'build/iteas');
const DATA = path.join(SRC, 'tests/data');
const seconds = Number(process.argv[2] || 60);
const connections = Number(process.argv[3] || 32);

const payloads = [
  { name: 'Box.glb (12 tris, iteas)', file: 'Box.glb', query: '' },
  { name: 'eight.off (1.5k tris, iteas)', file: 'eight.off', query: '' },
  { name: 'knight (1k tris, uniform 2)', file: 'decimated-knight.off', query: 'mode=uniform&levels=2' },
  { name: 'Avocado draco (682 tris, iteas)', file: 'Avocado.notex.draco.glb', query: '' },
  { name: 'bunny-npm (3.7k tris, iteas)', file: 'bunny-npm.obj', query: '' },
  { name: 'bunny-npm (3.7k tris, uniform 3)', file: 'bunny-npm.obj', query: 'mode=uniform&levels=3' },
].map((p) => ({ ...p, body: fs.readFileSync(path.join(DATA, p.file)) }));

const rss = (pid) => {
  const m = fs.readFileSync(`/proc/${pid}/status`, 'utf8').match(/VmRSS:\s+(\d+) kB/);
  return m ? Number(m[1]) / 1024 : 0;
};
const pct = (sorted, p) => sorted[Math.min(sorted.length - 1, Math.floor((p / 100) * sorted.length))];
const median = (a) => [...a].sort((x, y) => x - y)[Math.floor(a.length / 2)];

const proc = spawn(BIN, ['serve', '--port', '0', '--queue', String(2 * connections)], { stdio: ['ignore', 'pipe', 'inherit'] });
const port = await new Promise((resolve, reject) => {
  let out = '';
  proc.stdout.on('data', (d) => { out += d; const m = out.match(/listening on [^:]+:(\d+)/); if (m) resolve(Number(m[1])); });
  proc.on('exit', () => reject(new Error('server exited: ' + out)));
});
proc.stdout.resume();
const url = `http://127.0.0.1:${port}`;

// --- server vs CLI on the same ~100k-triangle job, idle machine ---------------
const eight = fs.readFileSync(path.join(DATA, 'eight.off'));
const cliTimes = [], srvTimes = [];
const outFile = path.join(os.tmpdir(), 'iteas-load-cli.glb');
for (let i = 0; i < 9; i++) {
  let t0 = performance.now();
  // (All cores, as the server gives a job that runs alone: the refinement on
  // them, the one primitive's Draco encoding on one.)
  const r = spawnSync(BIN, ['refine', path.join(DATA, 'eight.off'), '-o', outFile, '--mode', 'uniform', '--levels', '3', '--quiet']);
  if (r.status !== 0) throw new Error('cli failed');
  cliTimes.push(performance.now() - t0);
  t0 = performance.now();
  const res = await fetch(`${url}/v1/refine?mode=uniform&levels=3`, { method: 'POST', body: eight, headers: { 'Content-Type': 'application/octet-stream' } });
  await res.arrayBuffer();
  if (res.status !== 200) throw new Error('server failed ' + res.status);
  srvTimes.push(performance.now() - t0);
}

// --- the load ------------------------------------------------------------------
const latencies = [];
const statuses = {};
let failed = 0;
const errors = {};  // transport errors by their cause
const samples = [];
const t0 = Date.now();
const deadline = t0 + seconds * 1000;
const sampler = setInterval(() => samples.push({ t: (Date.now() - t0) / 1000, rss: rss(proc.pid) }), 2000);
async function client(k) {
  let i = k;
  while (Date.now() < deadline) {
    const p = payloads[i++ % payloads.length];
    const start = performance.now();
    try {
      const res = await fetch(`${url}/v1/refine?${p.query}`, { method: 'POST', body: p.body, headers: { 'Content-Type': 'application/octet-stream' } });
      await res.arrayBuffer();
      statuses[res.status] = (statuses[res.status] || 0) + 1;
      if (res.status !== 200) failed++;
      else latencies.push(performance.now() - start);
    } catch (e) {
      failed++;
      const why = `${e.cause?.code || ''} ${e.cause?.message || e.message}`.trim();
      errors[why] = (errors[why] || 0) + 1;
    }
  }
}
await Promise.all(Array.from({ length: connections }, (_, k) => client(k)));
clearInterval(sampler);
const elapsed = (Date.now() - t0) / 1000;
proc.kill('SIGTERM');
await new Promise((r) => proc.on('exit', r));

latencies.sort((a, b) => a - b);
const warm = samples.filter((s) => s.t >= Math.min(10, seconds / 4));
console.log(`load: ${seconds}s, ${connections} connections, ${payloads.length} payloads (small and medium), loopback`);
console.log(`requests: ${latencies.length + failed}, ok ${latencies.length}, failed ${failed}, statuses ${JSON.stringify(statuses)}` +
  (Object.keys(errors).length ? `, transport errors ${JSON.stringify(errors)}` : ''));
console.log(`throughput: ${(latencies.length / elapsed).toFixed(1)} requests/s`);
console.log(`latency: p50 ${pct(latencies, 50).toFixed(1)} ms, p99 ${pct(latencies, 99).toFixed(1)} ms`);
console.log(`server RSS after warm-up (MiB): first ${warm[0]?.rss.toFixed(1)}, min ${Math.min(...warm.map((s) => s.rss)).toFixed(1)}, ` +
            `max ${Math.max(...warm.map((s) => s.rss)).toFixed(1)}, last ${warm.at(-1)?.rss.toFixed(1)}`);
console.log(`RSS samples (s:MiB): ${samples.map((s) => `${s.t.toFixed(0)}:${s.rss.toFixed(0)}`).join(' ')}`);
const cli = median(cliTimes), srv = median(srvTimes);
console.log(`same job (eight.off, uniform 3 levels, 98,304 triangles): CLI median ${cli.toFixed(1)} ms (process start, all cores), ` +
            `server median ${srv.toFixed(1)} ms (HTTP round trip, a job alone: all cores): overhead ${(100 * (srv - cli) / cli).toFixed(1)} %`);
