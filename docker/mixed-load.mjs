// Mixed load through a load balancer (issue 7, point 2): synchronous refines
// and the job API (submit, poll, fetch the result) from several clients for a
// fixed time. Prints one JSON line of counts and latencies; exit 1 on any failure.
//   node docker/mixed-load.mjs URL SECONDS CLIENTS MESH...
import fs from 'node:fs';
import path from 'node:path';

const [url, seconds = '120', clients = '8', ...meshes] = process.argv.slice(2);
const TYPES = { '.glb': 'model/gltf-binary', '.gltf': 'model/gltf+json', '.obj': 'model/obj', '.stl': 'model/stl', '.ply': 'application/ply' };
const bodies = meshes.map((m) => ({ name: path.basename(m), bytes: fs.readFileSync(m), type: TYPES[path.extname(m)] || 'application/octet-stream' }));
const deadline = Date.now() + Number(seconds) * 1000;
const counts = { sync_ok: 0, job_ok: 0, polls: 0, failed: 0 };
const failures = [];
const latencies = [];

function fail(what) {
  counts.failed++;
  if (failures.length < 20) failures.push(what);
}

async function oneSync(mesh) {
  const t0 = Date.now();
  const r = await fetch(`${url}/v1/refine?levels=2`, { method: 'POST', body: mesh.bytes, headers: { 'Content-Type': mesh.type } });
  const body = Buffer.from(await r.arrayBuffer());
  if (r.status !== 200 || body.subarray(0, 4).toString() !== 'glTF') return fail(`sync ${mesh.name}: ${r.status} ${body.subarray(0, 200)}`);
  latencies.push(Date.now() - t0);
  counts.sync_ok++;
}

async function oneJob(mesh) {
  const t0 = Date.now();
  // The raw body, not multipart: Node 18's fetch ends multipart bodies in a way
  // Debian's cpp-httplib 0.11 refuses (see the README's HTTP notes).
  const r = await fetch(`${url}/v1/jobs?levels=3`, { method: 'POST', body: mesh.bytes, headers: { 'Content-Type': mesh.type } });
  if (r.status !== 202) return fail(`submit ${mesh.name}: ${r.status} ${await r.text()}`);
  const { id } = await r.json();
  for (let i = 0; i < 600; ++i) {
    const s = await fetch(`${url}/v1/jobs/${id}`);
    counts.polls++;
    if (s.status !== 200) return fail(`poll ${id}: ${s.status} ${await s.text()}`);
    const st = await s.json();
    if (st.status === 'done') {
      const res = await fetch(`${url}/v1/jobs/${id}/result`);
      const body = Buffer.from(await res.arrayBuffer());
      if (res.status !== 200 || body.subarray(0, 4).toString() !== 'glTF') return fail(`result ${id}: ${res.status}`);
      const del = await fetch(`${url}/v1/jobs/${id}`, { method: 'DELETE' });
      if (del.status !== 200) return fail(`delete ${id}: ${del.status}`);
      latencies.push(Date.now() - t0);
      counts.job_ok++;
      return;
    }
    if (st.status !== 'queued' && st.status !== 'running') return fail(`job ${id} ended ${st.status}: ${JSON.stringify(st.error)}`);
    await new Promise((resolve) => setTimeout(resolve, 100));
  }
  fail(`job ${id} did not finish`);
}

async function client(k) {
  let i = k;
  while (Date.now() < deadline) {
    const mesh = bodies[i % bodies.length];
    try {
      await (i % 2 ? oneJob(mesh) : oneSync(mesh));
    } catch (e) {
      fail(`${i % 2 ? 'job' : 'sync'} ${mesh.name}: ${e.message}`);
    }
    ++i;
  }
}

await Promise.all(Array.from({ length: Number(clients) }, (_, k) => client(k)));
latencies.sort((a, b) => a - b);
const q = (p) => latencies[Math.min(latencies.length - 1, Math.floor(p * latencies.length))] ?? 0;
console.log(JSON.stringify({ ...counts, p50_ms: q(0.5), p99_ms: q(0.99), failures }));
process.exit(counts.failed ? 1 : 0);
