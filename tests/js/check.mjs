// Independent checks of IteAS outputs with third-party tools: the Khronos glTF
// Validator and Google's draco3d decoder. Used by the node:test suites here.
import { execFileSync, spawn, spawnSync } from 'node:child_process';
import fs from 'node:fs';
import path from 'node:path';
import os from 'node:os';
import validator from 'gltf-validator';
import draco3d from 'draco3d';

export const SOURCE_DIR = process.env.ITEAS_SOURCE_DIR || path.resolve(path.dirname(new URL(import.meta.url).pathname), '../..');
export const BIN = process.env.ITEAS_BIN || path.join(SOURCE_DIR, 'build/iteas');
export const DATA = path.join(SOURCE_DIR, 'tests/data');
export const CORPUS = process.env.ITEAS_CORPUS || path.join(SOURCE_DIR, '../shared/meshes');
export const HAVE_CORPUS = fs.existsSync(CORPUS);

export function listFiles(dir) {
  if (!fs.existsSync(dir)) return [];
  return fs.readdirSync(dir).filter((f) => !f.endsWith('.md')).map((f) => path.join(dir, f))
    .filter((f) => fs.statSync(f).isFile()).sort();
}

export function validMeshes() {
  const files = listFiles(DATA);
  if (HAVE_CORPUS) for (const s of ['gltf', 'gltf-draco', 'drc', 'classic', 'classic-converted']) files.push(...listFiles(path.join(CORPUS, s)));
  return files;
}

export function nastyMeshes() {
  const files = listFiles(path.join(DATA, 'nasty'));
  if (HAVE_CORPUS) files.push(...listFiles(path.join(CORPUS, 'nasty')));
  return files;
}

export const tmp = fs.mkdtempSync(path.join(os.tmpdir(), 'iteas-test-'));
// Removed when the test process ends (a corpus run leaves about 150 MB there);
// ITEAS_KEEP_TMP=1 keeps it to look at.
if (!process.env.ITEAS_KEEP_TMP)
  process.on('exit', () => {
    try {
      fs.rmSync(tmp, { recursive: true, force: true, maxRetries: 3 });
    } catch {
      // a server still writing there as the process ends: the directory stays
    }
  });

export function iteas(args) {
  const r = spawnSync(BIN, args, { encoding: 'utf8', maxBuffer: 1 << 28 });
  return { code: r.status, signal: r.signal, stdout: r.stdout, stderr: r.stderr };
}

export function inspect(file) {
  return JSON.parse(execFileSync(BIN, ['inspect', file], { encoding: 'utf8', maxBuffer: 1 << 28 }));
}

// --- glTF container -------------------------------------------------------
export function parseGltf(bytes) {
  if (bytes.readUInt32LE(0) === 0x46546c67) {
    const jsonLen = bytes.readUInt32LE(12);
    const json = JSON.parse(bytes.subarray(20, 20 + jsonLen).toString('utf8'));
    let bin = null;
    const off = 20 + jsonLen;
    if (off + 8 <= bytes.length && bytes.readUInt32LE(off + 4) === 0x004e4942) bin = bytes.subarray(off + 8, off + 8 + bytes.readUInt32LE(off));
    return { json, buffers: [bin] };
  }
  const json = JSON.parse(bytes.toString('utf8'));
  const buffers = (json.buffers || []).map((b) => Buffer.from(b.uri.split(',')[1], 'base64'));
  return { json, buffers };
}

function viewBytes(g, viewIndex) {
  const v = g.json.bufferViews[viewIndex];
  return g.buffers[v.buffer || 0].subarray(v.byteOffset || 0, (v.byteOffset || 0) + v.byteLength);
}

const COMPONENTS = { SCALAR: 1, VEC2: 2, VEC3: 3, VEC4: 4 };

export function readFloatAccessor(g, index) {
  const a = g.json.accessors[index];
  if (a.componentType !== 5126) throw new Error('not a float accessor');
  const bytes = viewBytes(g, a.bufferView);
  const n = a.count * COMPONENTS[a.type];
  const out = new Float32Array(n);
  for (let i = 0; i < n; i++) out[i] = bytes.readFloatLE((a.byteOffset || 0) + 4 * i);
  return out;
}

// --- validators -------------------------------------------------------------
export async function validate(bytes) {
  const report = await validator.validateBytes(new Uint8Array(bytes), {
    maxIssues: 50,
    externalResourceFunction: () => Promise.reject(new Error('external resources are not loaded')),
  });
  return report.issues;
}

let dracoModule = null;
export async function decodeDraco(bytes) {
  if (!dracoModule) dracoModule = await draco3d.createDecoderModule({});
  const m = dracoModule;
  const decoder = new m.Decoder();
  const mesh = new m.Mesh();
  const data = new Int8Array(bytes.buffer, bytes.byteOffset, bytes.byteLength);
  const status = decoder.DecodeArrayToMesh(data, data.byteLength, mesh);
  if (!status.ok()) throw new Error('draco3d: ' + status.error_msg());
  const result = { points: mesh.num_points(), faces: mesh.num_faces(), attributes: {} };
  result.get = (uniqueId) => {
    const att = decoder.GetAttributeByUniqueId(mesh, uniqueId);
    if (!att || att.ptr === 0) return null;
    const n = att.num_components();
    const arr = new m.DracoFloat32Array();
    decoder.GetAttributeFloatForAllPoints(mesh, att, arr);
    const out = new Float32Array(result.points * n);
    for (let i = 0; i < out.length; i++) out[i] = arr.GetValue(i);
    m.destroy(arr);
    return { components: n, data: out };
  };
  result.free = () => { m.destroy(mesh); m.destroy(decoder); };
  return result;
}

// Checks one glTF/GLB output: validator errors, Draco payloads against the
// JSON's counts. Returns { errors, triangles, vertices, attributes, positions }.
export async function checkGltfOutput(file) {
  const bytes = fs.readFileSync(file);
  const issues = await validate(bytes);
  const g = parseGltf(bytes);
  const facts = { errors: issues.numErrors, messages: issues.messages.filter((x) => x.severity === 0), triangles: 0, vertices: 0, attributes: new Set(), draco: 0, positions: [] };
  for (const mesh of g.json.meshes || []) {
    for (const prim of mesh.primitives) {
      if ((prim.mode ?? 4) !== 4) continue;
      for (const k of Object.keys(prim.attributes)) facts.attributes.add(k);
      const ext = prim.extensions && prim.extensions.KHR_draco_mesh_compression;
      const indices = g.json.accessors[prim.indices];
      const pos = g.json.accessors[prim.attributes.POSITION];
      facts.triangles += indices.count / 3;
      facts.vertices += pos.count;
      if (ext) {
        facts.draco++;
        const d = await decodeDraco(viewBytes(g, ext.bufferView));
        try {
          if (d.faces * 3 !== indices.count) throw new Error(`Draco faces ${d.faces} vs indices count ${indices.count}/3`);
          for (const [sem, id] of Object.entries(ext.attributes)) {
            const acc = g.json.accessors[prim.attributes[sem]];
            if (d.points !== acc.count) throw new Error(`Draco points ${d.points} vs ${sem} count ${acc.count}`);
            const att = d.get(id);
            if (!att) throw new Error(`Draco attribute ${id} (${sem}) missing`);
            if (att.components !== COMPONENTS[acc.type]) throw new Error(`${sem} components differ`);
            if (sem === 'POSITION') {
              for (let k = 0; k < 3; k++) {
                let lo = Infinity, hi = -Infinity;
                for (let i = 0; i < d.points; i++) { lo = Math.min(lo, att.data[3 * i + k]); hi = Math.max(hi, att.data[3 * i + k]); }
                if (Math.abs(lo - acc.min[k]) > 1e-6 * (1 + Math.abs(lo)) || Math.abs(hi - acc.max[k]) > 1e-6 * (1 + Math.abs(hi)))
                  throw new Error(`POSITION min/max differ from the decoded data`);
              }
              facts.positions.push(att.data);
            }
          }
        } finally { d.free(); }
      } else {
        facts.positions.push(readFloatAccessor(g, prim.attributes.POSITION));
      }
    }
  }
  return facts;
}

// Largest distance from any point of |a| to the nearest point of |b| (grid hash).
export function maxNearestDistance(a, b, cell) {
  const key = (x, y, z) => `${Math.floor(x / cell)},${Math.floor(y / cell)},${Math.floor(z / cell)}`;
  const grid = new Map();
  for (let i = 0; i < b.length; i += 3) {
    const k = key(b[i], b[i + 1], b[i + 2]);
    if (!grid.has(k)) grid.set(k, []);
    grid.get(k).push(i);
  }
  let worst = 0;
  for (let i = 0; i < a.length; i += 3) {
    let best = Infinity;
    for (let dx = -1; dx <= 1; dx++) for (let dy = -1; dy <= 1; dy++) for (let dz = -1; dz <= 1; dz++) {
      const list = grid.get(key(a[i] + dx * cell, a[i + 1] + dy * cell, a[i + 2] + dz * cell));
      if (!list) continue;
      for (const j of list) best = Math.min(best, Math.hypot(a[i] - b[j], a[i + 1] - b[j + 1], a[i + 2] - b[j + 2]));
    }
    worst = Math.max(worst, best);
  }
  return worst;
}

export function concat(arrays) {
  const n = arrays.reduce((s, a) => s + a.length, 0);
  const out = new Float32Array(n);
  let o = 0;
  for (const a of arrays) { out.set(a, o); o += a.length; }
  return out;
}

// --- a server process on a free loopback port ---------------------------------
// Every server started here, so a failed test cannot leave one running (which
// would keep the test process, and CI, waiting for it).
const live = new Set();
export function killLeftoverServers() {
  for (const proc of live) if (proc.exitCode === null && proc.signalCode === null) proc.kill('SIGKILL');
  live.clear();
}

// |fileSizeKiB|: the server runs under that file size limit (ulimit -f), with
// SIGXFSZ as a shell gives it (Node ignores it, which its children inherit).
export async function startServer(flags = [], env = {}, { fileSizeKiB } = {}) {
  const args = ['serve', '--port', '0', ...flags];
  const [cmd, argv] = fileSizeKiB === undefined ? [BIN, args]
    : ['env', ['--default-signal=XFSZ', 'bash', '-c', `ulimit -f ${fileSizeKiB}; exec "$0" "$@"`, BIN, ...args]];
  const proc = spawn(cmd, argv, { env: { ...process.env, ...env }, stdio: ['ignore', 'pipe', 'pipe'] });
  live.add(proc);
  proc.on('exit', () => live.delete(proc));
  let out = '';
  proc.stdout.on('data', (d) => { out += d; });
  proc.stderr.on('data', (d) => { out += d; });
  const port = await new Promise((resolve, reject) => {
    const timer = setTimeout(() => reject(new Error('server did not start: ' + out)), 10000);
    proc.stdout.on('data', () => {
      const m = out.match(/listening on [^:]+:(\d+)|"event":"listening".*?"port":(\d+)/);  // text or JSON log
      if (m) { clearTimeout(timer); resolve(Number(m[1] ?? m[2])); }
    });
    proc.on('exit', (code) => { clearTimeout(timer); reject(new Error(`server exited ${code}: ${out}`)); });
  });
  return { proc, port, url: `http://127.0.0.1:${port}`, log: () => out };
}

// The server writes a request's log line after its response, and the line
// reaches us through a pipe: wait (up to |ms|) until |test| holds for the log,
// and hand back the log as it then is.
export async function logWhen(s, test, ms = 15000) {
  for (const end = Date.now() + ms; !test(s.log()) && Date.now() < end;) await new Promise((r) => setTimeout(r, 20));
  return s.log();
}

export async function stopServer(s) {
  let code = s.proc.exitCode ?? s.proc.signalCode;
  if (code === null) {
    const exited = new Promise((resolve) => s.proc.on('exit', (c, signal) => resolve(c ?? signal)));
    s.proc.kill('SIGTERM');
    code = await exited;
  }
  // A sanitizer's report, or whatever else made it fail, is in its log.
  if (code !== 0) process.stderr.write(`server exited ${code}; its log:\n${s.log()}\n`);
  return code;
}
