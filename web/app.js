// The IteAS page: upload a mesh, refine it through the job API, compare the
// input and the result side by side, read the statistics. three.js and its
// loaders are vendored into the build (no CDN).
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { DRACOLoader } from 'three/addons/loaders/DRACOLoader.js';
import { OBJLoader } from 'three/addons/loaders/OBJLoader.js';
import { PLYLoader } from 'three/addons/loaders/PLYLoader.js';
import { STLLoader } from 'three/addons/loaders/STLLoader.js';

const $ = (id) => document.getElementById(id);
const draco = new DRACOLoader().setDecoderPath('./vendor/three/examples/jsm/libs/draco/');
const gltfLoader = new GLTFLoader().setDRACOLoader(draco);
const LEVEL_COLOURS = ['#8d99a6', '#2f7bd8', '#19a974', '#e8b10e', '#f26b21', '#d7263d', '#9b3fc1', '#5b2a86', '#222222'];

// --- a view: renderer, camera, orbit controls --------------------------------
class View {
  constructor(element) {
    this.element = element;
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(window.devicePixelRatio || 1);
    this.renderer.setClearColor(0xffffff);
    element.appendChild(this.renderer.domElement);
    this.scene = new THREE.Scene();
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x445566, 1.6));
    const sun = new THREE.DirectionalLight(0xffffff, 1.8);
    sun.position.set(1, 2, 1.5);
    this.scene.add(sun);
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.001, 1000);
    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.addEventListener('change', () => this.render());
    this.root = null;
    new ResizeObserver(() => this.resize()).observe(element);
    this.resize();
  }
  resize() {
    const w = this.element.clientWidth || 400, h = this.element.clientHeight || 300;
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }
  show(object) {
    if (this.root) this.scene.remove(this.root);
    this.root = object;
    this.scene.add(object);
    this.render();
  }
  frame(box) {  // same framing for both views, from the input's bounds
    const size = box.getSize(new THREE.Vector3()).length() || 1;
    const centre = box.getCenter(new THREE.Vector3());
    this.camera.near = size / 1000;
    this.camera.far = size * 100;
    this.camera.position.copy(centre).add(new THREE.Vector3(0.6, 0.45, 1).normalize().multiplyScalar(size * 1.25));
    this.camera.updateProjectionMatrix();
    this.controls.target.copy(centre);
    this.controls.update();
    this.render();
  }
  follow(other) {  // orbit both views together
    let busy = false;
    other.controls.addEventListener('change', () => {
      if (busy) return;
      busy = true;
      this.camera.position.copy(other.camera.position);
      this.controls.target.copy(other.controls.target);
      this.controls.update();
      busy = false;
    });
  }
  render() { this.renderer.render(this.scene, this.camera); }
}

const viewIn = new View($('view-in'));
const viewOut = new View($('view-out'));
viewIn.follow(viewOut);
viewOut.follow(viewIn);

// --- geometry helpers ------------------------------------------------------------
const surfaceMaterial = (options = {}) =>
  new THREE.MeshStandardMaterial({ color: 0xb9c4cf, roughness: 0.55, metalness: 0.05, side: THREE.DoubleSide, ...options });

function meshesOf(object) {
  const out = [];
  object.updateMatrixWorld(true);
  object.traverse((o) => { if (o.isMesh) out.push(o); });
  return out;
}

function triangleCount(object) {
  let n = 0;
  for (const m of meshesOf(object)) {
    const g = m.geometry;
    n += (g.index ? g.index.count : g.attributes.position.count) / 3;
  }
  return n;
}

// World-space triangles as a flat Float32Array of 9 numbers each.
function worldTriangles(object) {
  const parts = [];
  const v = new THREE.Vector3();
  for (const m of meshesOf(object)) {
    const g = m.geometry, pos = g.attributes.position, idx = g.index;
    const n = idx ? idx.count : pos.count;
    const out = new Float32Array(n * 3);
    for (let i = 0; i < n; ++i) {
      v.fromBufferAttribute(pos, idx ? idx.getX(i) : i).applyMatrix4(m.matrixWorld);
      out[3 * i] = v.x; out[3 * i + 1] = v.y; out[3 * i + 2] = v.z;
    }
    parts.push(out);
  }
  const total = parts.reduce((s, p) => s + p.length, 0);
  const all = new Float32Array(total);
  let o = 0;
  for (const p of parts) { all.set(p, o); o += p.length; }
  return all;
}

function area(t, i) {
  const ax = t[i + 3] - t[i], ay = t[i + 4] - t[i + 1], az = t[i + 5] - t[i + 2];
  const bx = t[i + 6] - t[i], by = t[i + 7] - t[i + 1], bz = t[i + 8] - t[i + 2];
  const cx = ay * bz - az * by, cy = az * bx - ax * bz, cz = ax * by - ay * bx;
  return 0.5 * Math.sqrt(cx * cx + cy * cy + cz * cz);
}

// Squared distance from point p to triangle t[i..i+8] (Ericson, Real-Time
// Collision Detection, 5.1.5).
function pointTriangleDistance2(px, py, pz, t, i) {
  const ax = t[i], ay = t[i + 1], az = t[i + 2], bx = t[i + 3], by = t[i + 4], bz = t[i + 5];
  const cx = t[i + 6], cy = t[i + 7], cz = t[i + 8];
  const abx = bx - ax, aby = by - ay, abz = bz - az, acx = cx - ax, acy = cy - ay, acz = cz - az;
  const apx = px - ax, apy = py - ay, apz = pz - az;
  const d1 = abx * apx + aby * apy + abz * apz, d2 = acx * apx + acy * apy + acz * apz;
  const d2p = (qx, qy, qz) => (px - qx) ** 2 + (py - qy) ** 2 + (pz - qz) ** 2;
  if (d1 <= 0 && d2 <= 0) return d2p(ax, ay, az);
  const bpx = px - bx, bpy = py - by, bpz = pz - bz;
  const d3 = abx * bpx + aby * bpy + abz * bpz, d4 = acx * bpx + acy * bpy + acz * bpz;
  if (d3 >= 0 && d4 <= d3) return d2p(bx, by, bz);
  const vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) { const v = d1 / (d1 - d3); return d2p(ax + v * abx, ay + v * aby, az + v * abz); }
  const cpx = px - cx, cpy = py - cy, cpz = pz - cz;
  const d5 = abx * cpx + aby * cpy + abz * cpz, d6 = acx * cpx + acy * cpy + acz * cpz;
  if (d6 >= 0 && d5 <= d6) return d2p(cx, cy, cz);
  const vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) { const w = d2 / (d2 - d6); return d2p(ax + w * acx, ay + w * acy, az + w * acz); }
  const va = d3 * d6 - d5 * d4;
  if (va <= 0 && d4 - d3 >= 0 && d5 - d6 >= 0) {
    const w = (d4 - d3) / (d4 - d3 + (d5 - d6));
    return d2p(bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz));
  }
  const denom = 1 / (va + vb + vc), v = vb * denom, w = vc * denom;
  return d2p(ax + abx * v + acx * w, ay + aby * v + acy * w, az + abz * v + acz * w);
}

// The refinement level of each output triangle, estimated as log4 of the area
// of the input triangle it lies on (the closest one to its centroid, searched
// through a uniform grid of input triangles) over its own: every level splits a
// triangle into four of about a quarter of the area.
function estimateLevels(input, output, maxLevel) {
  const nIn = input.length / 9, nOut = output.length / 9;
  const box = new THREE.Box3();
  for (let i = 0; i < input.length; i += 3) box.expandByPoint(new THREE.Vector3(input[i], input[i + 1], input[i + 2]));
  const size = box.getSize(new THREE.Vector3());
  const cells = Math.max(1, Math.round(Math.cbrt(nIn / 2)));
  const cell = Math.max(size.x, size.y, size.z) / cells || 1;
  const cellOf = (v, lo) => Math.floor((v - lo) / cell);
  const grid = new Map();
  const aIn = new Float32Array(nIn);
  for (let f = 0; f < nIn; ++f) {  // each input triangle in every cell its bounding box touches
    const i = 9 * f;
    aIn[f] = area(input, i);
    const lo = [0, 1, 2].map((k) => cellOf(Math.min(input[i + k], input[i + 3 + k], input[i + 6 + k]), box.min.getComponent(k)));
    const hi = [0, 1, 2].map((k) => cellOf(Math.max(input[i + k], input[i + 3 + k], input[i + 6 + k]), box.min.getComponent(k)));
    for (let x = lo[0]; x <= hi[0]; ++x) for (let y = lo[1]; y <= hi[1]; ++y) for (let z = lo[2]; z <= hi[2]; ++z) {
      const key = `${x},${y},${z}`;
      if (!grid.has(key)) grid.set(key, []);
      grid.get(key).push(f);
    }
  }
  const levels = new Uint8Array(nOut);
  for (let f = 0; f < nOut; ++f) {
    const i = 9 * f;
    const x = (output[i] + output[i + 3] + output[i + 6]) / 3, y = (output[i + 1] + output[i + 4] + output[i + 7]) / 3,
          z = (output[i + 2] + output[i + 5] + output[i + 8]) / 3;
    const gx = cellOf(x, box.min.x), gy = cellOf(y, box.min.y), gz = cellOf(z, box.min.z);
    let best = -1, bestD = Infinity;
    for (let r = 0; r <= 2 && (best < 0 || r === 1); ++r)
      for (let dx = -r; dx <= r; ++dx) for (let dy = -r; dy <= r; ++dy) for (let dz = -r; dz <= r; ++dz) {
        if (Math.max(Math.abs(dx), Math.abs(dy), Math.abs(dz)) !== r) continue;  // the shell of radius r
        const list = grid.get(`${gx + dx},${gy + dy},${gz + dz}`);
        if (!list) continue;
        for (const g of list) {
          const d = pointTriangleDistance2(x, y, z, input, 9 * g);
          if (d < bestD) { bestD = d; best = g; }
        }
      }
    const a = area(output, i);
    levels[f] = best < 0 || a <= 0 ? 0 : Math.max(0, Math.min(maxLevel, Math.round(Math.log(aIn[best] / a) / Math.log(4))));
  }
  return levels;
}

// One non-indexed mesh for the output view, with a colour per face (its
// level) when |levels| is given.
function outputMesh(triangles, levels) {
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.BufferAttribute(triangles, 3));
  if (levels) {
    const colours = new Float32Array(triangles.length);
    const c = new THREE.Color();
    for (let f = 0; f < levels.length; ++f) {
      c.set(LEVEL_COLOURS[levels[f]]);
      for (let k = 0; k < 3; ++k) colours.set([c.r, c.g, c.b], 9 * f + 3 * k);
    }
    g.setAttribute('color', new THREE.BufferAttribute(colours, 3));
  }
  g.computeVertexNormals();
  return new THREE.Mesh(g, surfaceMaterial(levels ? { vertexColors: true, color: 0xffffff, flatShading: true } : { flatShading: true }));
}

// --- reading the input in the browser ----------------------------------------------
function parseOff(text) {
  const words = text.replace(/#[^\n]*/g, ' ').split(/\s+/).filter(Boolean);
  let i = words[0] && words[0].endsWith('OFF') ? 1 : 0;
  const nv = +words[i++], nf = +words[i++]; i++;
  const p = [];
  for (let v = 0; v < nv; ++v) p.push(+words[i++], +words[i++], +words[i++]);
  const index = [];
  for (let f = 0; f < nf; ++f) {
    const k = +words[i++], poly = [];
    for (let j = 0; j < k; ++j) poly.push(+words[i++]);
    for (let j = 1; j + 1 < k; ++j) index.push(poly[0], poly[j], poly[j + 1]);
  }
  const g = new THREE.BufferGeometry();
  g.setAttribute('position', new THREE.Float32BufferAttribute(p, 3));
  g.setIndex(index);
  return g;
}

async function readInput(file) {
  const buffer = await file.arrayBuffer();
  const name = file.name.toLowerCase();
  const head = new TextDecoder().decode(new Uint8Array(buffer, 0, Math.min(16, buffer.byteLength)));
  const wrap = (geometry) => new THREE.Mesh(geometry, surfaceMaterial());
  if (head.startsWith('glTF') || name.endsWith('.gltf') || name.endsWith('.glb'))
    return (await gltfLoader.parseAsync(buffer, '')).scene;
  if (head.startsWith('DRACO') || name.endsWith('.drc'))
    return wrap(await new Promise((resolve, reject) => draco.parse(buffer, resolve, reject)));
  if (head.startsWith('ply')) return wrap(new PLYLoader().parse(buffer));
  if (head.startsWith('OFF') || name.endsWith('.off')) return wrap(parseOff(new TextDecoder().decode(buffer)));
  if (name.endsWith('.stl')) return wrap(new STLLoader().parse(buffer));
  return new OBJLoader().parse(new TextDecoder().decode(buffer));
}

// --- talking to the server ---------------------------------------------------------------
function headers() {
  const key = $('api-key').value.trim();
  return key ? { Authorization: `Bearer ${key}` } : {};
}

async function failure(response) {
  let message = `HTTP ${response.status}`;
  try {
    const body = await response.json();
    if (body && body.error) message = `${body.error.message} (${body.error.code}, HTTP ${body.error.status})`;
  } catch { /* not an envelope */ }
  return new Error(message);
}

function query(form) {
  const params = new URLSearchParams();
  for (const [k, v] of new FormData(form)) if (k !== 'api_key' && typeof v === 'string' && v.trim() !== '') params.set(k, v.trim());
  return params;
}

async function refine(file, params, onProgress) {
  const body = new FormData();
  body.append('mesh', file, file.name);
  const created = await fetch(`v1/jobs?${params}`, { method: 'POST', body, headers: headers() });
  if (!created.ok) throw await failure(created);
  const job = await created.json();
  const levels = Number(params.get('levels') || (params.get('mode') && params.get('mode') !== 'iteas' ? 2 : 6));
  for (;;) {
    const r = await fetch(`v1/jobs/${job.id}`, { headers: headers() });
    if (!r.ok) throw await failure(r);
    const status = await r.json();
    if (status.status === 'failed') throw new Error(`${status.error.message} (${status.error.code})`);
    if (status.status === 'cancelled') throw new Error('the job was cancelled');
    onProgress(status.progress, levels, status.status);
    if (status.status === 'done') {
      const result = await fetch(`v1/jobs/${job.id}/result`, { headers: headers() });
      if (!result.ok) throw await failure(result);
      return { stats: status.statistics, bytes: await result.arrayBuffer() };
    }
    await new Promise((resolve) => setTimeout(resolve, 200));
  }
}

// --- statistics -----------------------------------------------------------------------------
const fmt = (x, digits = 2) => (typeof x === 'number' ? (Number.isInteger(x) ? x.toLocaleString('en') : x.toFixed(digits)) : String(x ?? ''));

function showStats(stats) {
  const tbody = $('levels-table').querySelector('tbody');
  tbody.replaceChildren();
  for (const l of stats.levels) {
    const tr = document.createElement('tr');
    for (const v of [l.level, l.threshold, l.faces_selected, l.red_splits, l.green_splits, l.vertices_added,
      l.triangles_after, l.mean_theta_after, l.max_theta_after, l.ms]) {
      const td = document.createElement('td');
      td.textContent = fmt(v);
      tr.append(td);
    }
    tbody.append(tr);
  }
  const rows = [
    ['input triangles', stats.input.triangles], ['output triangles', stats.output.triangles],
    ['threshold T (°)', stats.threshold?.value ?? stats.threshold], ['stopped by', stats.stopped_by],
    ['uniform to the same level', stats.uniform?.triangles], ['fewer than uniform (%)', stats.uniform?.reduction_percent],
    ['mean θ before → after (°)', `${fmt(stats.smoothness.before.mean_theta)} → ${fmt(stats.smoothness.after.mean_theta)}`],
    ['min angle before → after (°)', `${fmt(stats.quality.before.min_angle)} → ${fmt(stats.quality.after.min_angle)}`],
    ['output bytes', stats.output.bytes], ['total ms', stats.timings_ms?.total],
  ];
  const sbody = $('summary-table').querySelector('tbody');
  sbody.replaceChildren();
  for (const [k, v] of rows) {
    const tr = document.createElement('tr');
    const th = document.createElement('th');
    th.textContent = k;
    const td = document.createElement('td');
    td.textContent = typeof v === 'object' && v !== null ? JSON.stringify(v) : fmt(v);
    td.dataset.key = k;
    tr.append(th, td);
    sbody.append(tr);
  }
  drawChart(stats);
}

function drawChart(stats) {
  const canvas = $('chart'), ctx = canvas.getContext('2d');
  const W = canvas.width, H = canvas.height, L = 56, R = 46, T = 22, B = 30;
  ctx.clearRect(0, 0, W, H);
  const pts = [{ level: 0, tris: stats.input.triangles, theta: stats.smoothness.before.mean_theta },
    ...stats.levels.map((l) => ({ level: l.level, tris: l.triangles_after, theta: l.mean_theta_after }))];
  const maxT = Math.max(...pts.map((p) => p.tris)), maxTheta = Math.max(...pts.map((p) => p.theta), 1e-9);
  const x = (i) => L + (pts.length === 1 ? 0 : (i * (W - L - R)) / (pts.length - 1));
  ctx.font = '12px system-ui, sans-serif';
  ctx.strokeStyle = '#c8d0d8';
  ctx.strokeRect(L, T, W - L - R, H - T - B);
  const bw = Math.min(36, (W - L - R) / pts.length / 2);
  pts.forEach((p, i) => {
    const h = ((H - T - B) * p.tris) / maxT;
    ctx.fillStyle = '#2f7bd8';
    ctx.fillRect(x(i) - bw / 2, H - B - h, bw, h);
    ctx.fillStyle = '#1d232a';
    ctx.fillText(String(p.level), x(i) - 4, H - B + 16);
  });
  ctx.strokeStyle = '#f26b21';
  ctx.lineWidth = 2;
  ctx.beginPath();
  pts.forEach((p, i) => {
    const y = H - B - ((H - T - B) * p.theta) / maxTheta;
    if (i) ctx.lineTo(x(i), y); else ctx.moveTo(x(i), y);
  });
  ctx.stroke();
  ctx.fillStyle = '#2f7bd8';
  ctx.fillText(`triangles (max ${maxT.toLocaleString('en')})`, L, 14);
  ctx.fillStyle = '#f26b21';
  ctx.fillText(`mean θ (max ${maxTheta.toFixed(2)}°)`, W - R - 150, 14);
  ctx.fillStyle = '#1d232a';
  ctx.fillText('level', 8, H - B + 16);
}

// --- the page's state -----------------------------------------------------------------------
let inputFile = null, inputObject = null, outputObject = null, outputLevels = null, outputTriangles = null;

function setError(message) {
  $('error').hidden = !message;
  $('error').textContent = message || '';
  if (message) document.body.dataset.state = 'error';
}

function applyDisplay() {
  const wire = $('wireframe').checked;
  for (const root of [inputObject, viewOut.root]) if (root) root.traverse((o) => { if (o.isMesh) o.material.wireframe = wire; });
  if (outputTriangles) {
    const mesh = outputMesh(outputTriangles, $('levels-colour').checked ? outputLevels : null);
    mesh.material.wireframe = wire;
    viewOut.show(mesh);
    const used = new Set(outputLevels);
    $('legend').innerHTML = $('levels-colour').checked
      ? [...used].sort().map((l) => `<span style="background:${LEVEL_COLOURS[l]}">L${l}</span>`).join('')
      : '';
  }
  viewIn.render();
  viewOut.render();
}

async function chooseFile(file) {
  setError('');
  inputFile = file;
  $('drop-text').textContent = file.name;
  $('run').disabled = false;
  try {
    inputObject = await readInput(file);
    inputObject.traverse((o) => { if (o.isMesh) o.material = surfaceMaterial(); });
    viewIn.show(inputObject);
    const box = new THREE.Box3().setFromObject(inputObject);
    viewIn.frame(box);
    viewOut.frame(box);
    $('in-count').textContent = `${triangleCount(inputObject).toLocaleString('en')} triangles`;
  } catch (e) {
    inputObject = null;
    $('in-count').textContent = '(this browser cannot preview it; the server may still read it)';
  }
}

$('file').addEventListener('change', (e) => { if (e.target.files[0]) chooseFile(e.target.files[0]); });
const drop = $('drop');
drop.addEventListener('dragover', (e) => { e.preventDefault(); drop.classList.add('over'); });
drop.addEventListener('dragleave', () => drop.classList.remove('over'));
drop.addEventListener('drop', (e) => {
  e.preventDefault();
  drop.classList.remove('over');
  if (e.dataTransfer.files[0]) chooseFile(e.dataTransfer.files[0]);
});
$('wireframe').addEventListener('change', applyDisplay);
$('levels-colour').addEventListener('change', applyDisplay);

$('form').addEventListener('submit', async (e) => {
  e.preventDefault();
  if (!inputFile) return;
  setError('');
  document.body.dataset.state = 'running';
  $('run').disabled = true;
  $('progress').hidden = false;
  $('progress').value = 0;
  $('download').hidden = true;
  try {
    const { stats, bytes } = await refine(inputFile, query($('form')), (p, levels, state) => {
      $('progress').value = state === 'done' ? 1 : Math.min(1, (Math.max(0, p.level - 1) + p.fraction) / levels);
      $('phase').textContent = state === 'queued' ? 'queued' : `level ${p.level}: ${p.phase}`;
    });
    const gltf = await gltfLoader.parseAsync(bytes.slice(0), '');
    outputObject = gltf.scene;
    outputTriangles = worldTriangles(outputObject);
    outputLevels = inputObject ? estimateLevels(worldTriangles(inputObject), outputTriangles, stats.levels.length) : new Uint8Array(outputTriangles.length / 9);
    applyDisplay();
    $('out-count').textContent = `${triangleCount(outputObject).toLocaleString('en')} triangles`;
    showStats(stats);
    const url = URL.createObjectURL(new Blob([bytes], { type: 'model/gltf-binary' }));
    $('download').href = url;
    $('download').download = inputFile.name.replace(/\.[^.]*$/, '') + '.iteas.glb';
    $('download').hidden = false;
    $('phase').textContent = `done: ${stats.stopped_by}`;
    window.iteasResult = { stats, inputTriangles: inputObject ? triangleCount(inputObject) : null, outputTriangles: triangleCount(outputObject) };
    document.body.dataset.state = 'done';
  } catch (err) {
    setError(err.message);
    $('phase').textContent = '';
  } finally {
    $('run').disabled = false;
    $('progress').hidden = true;
  }
});
document.body.dataset.state = 'idle';
