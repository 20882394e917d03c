// The CLI over every mesh we have, checked by independent tools (issue 2
// points 2-3, issue 3 point 5). Runs on the shipped meshes, and on the whole
// corpus in ../shared/meshes when it is present.
import { test } from 'node:test';
import assert from 'node:assert/strict';
import fs from 'node:fs';
import path from 'node:path';
import { spawn, spawnSync } from 'node:child_process';
import {
  BIN, SOURCE_DIR, HAVE_CORPUS, DATA, tmp, iteas, inspect, validMeshes, nastyMeshes, validate, checkGltfOutput, maxNearestDistance, concat,
} from './check.mjs';

// ITEAS_JS_ONLY=broken runs only the broken-input test (used with the ASan build).
// ITEAS_JS_ONLY=a,b runs only the tests named a or b.
const only = (process.env.ITEAS_JS_ONLY || '').split(',').filter(Boolean);
const maybe = (name) => (only.length && !only.includes(name) ? test.skip : test);

const isGltf = (f) => /\.(glb|gltf)$/i.test(f);
const inputAttributes = (info) => {
  const s = new Set(['POSITION']);
  for (const m of info.per_mesh) for (const a of m.attributes) if (!a.includes(':')) s.add(a);
  return s;
};

maybe('convert')(`every valid mesh converts to plain and Draco GLB (${HAVE_CORPUS ? 'corpus present' : 'shipped meshes only'})`, async (t) => {
  for (const file of validMeshes()) {
    await t.test(path.basename(file) + ' ' + path.basename(path.dirname(file)), async () => {
      const r0 = iteas(['inspect', file]);
      if (r0.code === 3 && /no usable triangles|point cloud/.test(r0.stderr)) return;  // point clouds: refused with exit 3
      assert.equal(r0.code, 0, r0.stderr);
      const info = JSON.parse(r0.stdout);
      const inputErrors = isGltf(file) ? (await validate(fs.readFileSync(file))).numErrors : 0;
      const expected = info.triangles - info.dropped_faces;
      const out = {};
      for (const compression of ['none', 'draco']) {
        const o = path.join(tmp, `${path.basename(file)}.${compression}.glb`);
        const s = path.join(tmp, `${path.basename(file)}.${compression}.json`);
        const r = iteas(['convert', file, o, '--compression', compression, '--stats', s, '--quiet']);
        assert.equal(r.code, 0, r.stderr);
        const stats = JSON.parse(fs.readFileSync(s, 'utf8'));
        const facts = await checkGltfOutput(o);
        if (inputErrors === 0) assert.equal(facts.errors, 0, JSON.stringify(facts.messages.slice(0, 3)));
        assert.equal(facts.triangles, stats.output.triangles, 'statistics match the file');
        assert.equal(facts.vertices, stats.output.vertices, 'statistics match the file');
        assert.equal(stats.output.triangles + stats.output.triangles_collapsed_by_quantization, expected);
        assert.deepEqual([...facts.attributes].sort(), [...inputAttributes(info)].sort());
        if (compression === 'draco') assert.ok(facts.draco > 0 || info.per_mesh.every((m) => m.morph_targets > 0));
        out[compression] = facts;
      }
      // Positions equal within the quantization step (14 bits over the largest extent).
      const plain = concat(out.none.positions), dr = concat(out.draco.positions);
      let range = 0;
      for (let k = 0; k < 3; k++) {
        let lo = Infinity, hi = -Infinity;
        for (let i = k; i < plain.length; i += 3) { lo = Math.min(lo, plain[i]); hi = Math.max(hi, plain[i]); }
        range = Math.max(range, hi - lo);
      }
      const step = range / ((1 << 14) - 1);
      assert.ok(maxNearestDistance(dr, plain, Math.max(step * 2, 1e-12)) <= step * 0.87 + 1e-7 * range, 'Draco positions within one quantization step');
    });
  }
});

const MODES = [
  ['--mode', 'iteas'],
  ['--mode', 'uniform', '--levels', '2'],
  ['--mode', 'fixed', '--threshold', '10', '--levels', '2'],
  ['--mode', 'iteas', '--threshold-scope', 'level', '--crease-angle', '60', '--output', 'gltf', '--compression', 'none'],
];

maybe('refine')('iteas refine in every mode writes valid files whose statistics match them', async (t) => {
  for (const file of validMeshes()) {
    for (const mode of MODES) {
      await t.test(`${path.basename(file)} ${mode.join(' ')}`, async () => {
        const gltf = mode.includes('gltf');
        const o = path.join(tmp, `${path.basename(file)}.refined.${gltf ? 'gltf' : 'glb'}`);
        const s = o + '.json';
        const r = iteas(['refine', file, '-o', o, ...mode, '--max-triangles', '600000', '--stats', s, '--quiet']);
        if (r.code === 3 && /no usable triangles|point cloud/.test(r.stderr)) return;
        assert.equal(r.code, 0, r.stderr);
        const stats = JSON.parse(fs.readFileSync(s, 'utf8'));
        const facts = await checkGltfOutput(o);
        const inputErrors = isGltf(file) ? (await validate(fs.readFileSync(file))).numErrors : 0;
        if (inputErrors === 0) assert.equal(facts.errors, 0, JSON.stringify(facts.messages.slice(0, 3)));
        assert.equal(facts.triangles, stats.output.triangles);
        assert.equal(facts.vertices, stats.output.vertices);
        assert.ok(stats.output.triangles <= 600000 + 0);
        assert.ok(['converged', 'stalled', 'max_levels', 'budget'].includes(stats.stopped_by));
        if (gltf) {
          const embedded = JSON.parse(fs.readFileSync(o, 'utf8')).asset.extras.iteas;
          assert.equal(embedded.output.triangles, stats.output.triangles);
          assert.deepEqual(embedded.levels.map((l) => l.triangles_after), stats.levels.map((l) => l.triangles_after));
        }
      });
    }
  }
});

maybe('broken')('broken inputs end with exit code 3 and a one-line reason, or succeed with warnings', async (t) => {
  for (const file of nastyMeshes()) {
    await t.test(path.basename(file), () => {
      const o = path.join(tmp, path.basename(file) + '.out.glb');
      const r = iteas(['refine', file, '-o', o, '--levels', '2', '--stats', '-', '--quiet']);
      assert.equal(r.signal, null, 'no signal');
      if (r.code === 0) {
        const stats = JSON.parse(r.stdout);
        assert.ok(Array.isArray(stats.warnings));
      } else {
        assert.equal(r.code, 3, r.stderr);
        const lines = r.stderr.trim().split('\n');
        assert.equal(lines.length, 1, r.stderr);
        assert.match(lines[0], /^iteas: .+: .+ \([a-z_]+\)$/);
      }
    });
  }
});

maybe('usage')('usage errors exit 2 and unreadable files exit 4', () => {
  assert.equal(iteas(['refine']).code, 2);
  assert.equal(iteas(['refine', 'x.glb', '-o', 'y.glb', '--levels', '9']).code, 2);
  assert.equal(iteas(['refine', 'x.glb', '-o', 'y.glb', '--bogus', '1']).code, 2);
  assert.equal(iteas(['frobnicate']).code, 2);
  const version = iteas(['--version']);
  assert.equal(version.code, 0);
  const project = fs.readFileSync(path.join(SOURCE_DIR, 'CMakeLists.txt'), 'utf8').match(/project\(iteas VERSION ([0-9.]+)/)[1];
  assert.equal(version.stdout, `iteas ${project}\n`);
  assert.equal(iteas(['refine', path.join(tmp, 'does-not-exist.glb'), '-o', path.join(tmp, 'y.glb')]).code, 4);
  for (const bad of ['12Q', '5MB', '-1', ''])
    assert.equal(iteas(['refine', 'x.glb', '-o', 'y.glb', '--memory-limit', bad]).code, 2, bad);
  // A directory is refused as unreadable (it read as 2^63 bytes, and then as
  // a job past the memory limit), with the reason.
  const dir = iteas(['refine', tmp, '-o', path.join(tmp, 'y.glb')]);
  assert.equal(dir.code, 4, dir.stderr);
  assert.match(dir.stderr, /cannot read .+: Is a directory/);
  assert.match(iteas(['inspect', path.join(tmp, 'does-not-exist.glb')]).stderr, /No such file or directory/);
});

// OUT and --stats naming one file (directly, through "./", a hard or a
// symbolic link) or both stdout: the statistics replaced the mesh, exit 0.
maybe('usage')('OUT and --stats cannot be the same file', () => {
  const input = path.join(DATA, 'bunny-npm.obj');
  const dir = fs.mkdtempSync(path.join(tmp, 'same-'));
  const out = path.join(dir, 'out.glb');
  const run = (outArg, statsArg) => iteas(['refine', input, '-o', outArg, '--output', 'glb', '--stats', statsArg,
    '--mode', 'uniform', '--levels', '1', '--quiet']);
  for (const [o, st] of [[out, out], [out, path.join(dir, '.', 'out.glb')], ['-', '-']]) {
    const r = run(o, st);
    assert.equal(r.code, 2, `${o} ${st}: ${r.stderr}`);
    assert.match(r.stderr, /OUT and --stats (name the same file|cannot both be -)/);
  }
  assert.deepEqual(fs.readdirSync(dir), []);
  assert.equal(run(out, path.join(dir, 'stats.json')).code, 0);
  fs.linkSync(out, path.join(dir, 'hard.glb'));
  fs.symlinkSync(out, path.join(dir, 'soft.glb'));
  for (const other of ['hard.glb', 'soft.glb']) assert.equal(run(out, path.join(dir, other)).code, 2, other);
  assert.equal(fs.readFileSync(out).subarray(0, 4).toString(), 'glTF');
  assert.equal(run('/dev/null', '/dev/null').code, 0);
});

// "-" reads the input from stdin (the format told by its content).
maybe('usage')('the input can come from stdin', () => {
  const input = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const info = spawnSync(BIN, ['inspect', '-'], { input, encoding: 'utf8' });
  assert.equal(info.status, 0, info.stderr);
  assert.equal(JSON.parse(info.stdout).triangles, 3674);
  const out = path.join(tmp, 'from-stdin.glb');
  const r = spawnSync(BIN, ['refine', '-', '-o', out, '--mode', 'uniform', '--levels', '1', '--stats', '-', '--quiet'],
    { input, encoding: 'utf8' });
  assert.equal(r.status, 0, r.stderr);
  assert.equal(JSON.parse(r.stdout).output.triangles, 4 * 3674);
  assert.equal(fs.readFileSync(out).subarray(0, 4).toString(), 'glTF');
});

// A write that fails half way (here a file size limit of 100 KiB, as a full
// disk would) leaves the file that was there, and no temporary file; a
// device is written in place (renaming over /dev/null would replace it).
maybe('usage')('a failed write keeps the previous output whole', () => {
  const input = path.join(DATA, 'bunny-npm.obj');
  const dir = fs.mkdtempSync(path.join(tmp, 'write-'));
  const out = path.join(dir, 'out.glb');
  const stats = path.join(dir, 'stats.json');
  fs.writeFileSync(out, 'the previous output');
  const limited = (args) => {
    // SIGXFSZ as a shell gives it (Node ignores it, and its children would inherit that).
    const r = spawnSync('env', ['--default-signal=XFSZ', 'bash', '-c', 'ulimit -f 100; exec "$0" "$@"', BIN, ...args],
      { encoding: 'utf8' });
    return { code: r.status, stderr: r.stderr };
  };
  const r = limited(['refine', input, '-o', out, '--levels', '2', '--compression', 'none', '--quiet']);
  assert.equal(r.code, 4, r.stderr);
  assert.match(r.stderr, /cannot write .*out\.glb: File too large/);
  assert.equal(fs.readFileSync(out, 'utf8'), 'the previous output');
  assert.deepEqual(fs.readdirSync(dir), ['out.glb']);
  // A path that cannot be written fails before the job, the output untouched.
  const missing = iteas(['refine', input, '-o', out, '--stats', path.join(dir, 'no', 'stats.json'), '--quiet']);
  assert.equal(missing.code, 4, missing.stderr);
  assert.match(missing.stderr, /cannot write .+stats\.json: No such file or directory/);
  assert.equal(fs.readFileSync(out, 'utf8'), 'the previous output');
  const isDir = iteas(['refine', input, '-o', dir, '--output', 'glb', '--quiet']);
  assert.equal(isDir.code, 4, isDir.stderr);
  assert.match(isDir.stderr, /Is a directory/);
  // An output under the limit (Draco, 53 KB) replaces it, beside the statistics.
  const ok = limited(['refine', input, '-o', out, '--quiet', '--stats', stats]);
  assert.equal(ok.code, 0, ok.stderr);
  assert.equal(fs.readFileSync(out).subarray(0, 4).toString(), 'glTF');
  assert.deepEqual(fs.readdirSync(dir).sort(), ['out.glb', 'stats.json']);
  // A link keeps pointing at the file, which is replaced; the file keeps its mode.
  fs.chmodSync(out, 0o640);
  fs.symlinkSync(out, path.join(dir, 'link.glb'));
  const linked = iteas(['refine', input, '-o', path.join(dir, 'link.glb'), '--mode', 'uniform', '--levels', '1', '--quiet']);
  assert.equal(linked.code, 0, linked.stderr);
  assert.ok(fs.lstatSync(path.join(dir, 'link.glb')).isSymbolicLink());
  assert.equal(fs.statSync(out).mode & 0o777, 0o640);
  assert.equal(fs.statSync(out).size, fs.statSync(path.join(dir, 'link.glb')).size);
  assert.ok(fs.statSync(out).size < 53000, 'the uniform level-1 output replaced the file');
  assert.equal(iteas(['refine', input, '-o', '/dev/null', '--output', 'glb', '--quiet']).code, 0);
  assert.ok(fs.statSync('/dev/null').isCharacterDevice());
  assert.equal(iteas(['refine', input, '-o', '/dev/full', '--output', 'glb', '--quiet']).code, 4);
});

// SIGTERM while the output is being written (a pipeline's timeout) ends the
// process as the signal does, and removes the temporary file: nothing is left
// (a 68 MB uncompressed output, so that the write lasts long enough to be
// caught; the directory is polled until the temporary file shows).
maybe('usage')('a signal during the write leaves no temporary file', async () => {
  const input = path.join(DATA, 'bunny-npm.obj');
  for (let attempt = 1; ; ++attempt) {
    const dir = fs.mkdtempSync(path.join(tmp, 'signal-'));
    const child = spawn(BIN, ['refine', input, '-o', path.join(dir, 'big.glb'), '--mode', 'uniform', '--levels', '5',
      '--compression', 'none', '--quiet']);
    const ended = new Promise((resolve) => child.on('exit', (code, signal) => resolve({ code, signal })));
    let caught = false;
    for (const t0 = Date.now(); Date.now() - t0 < 60000;) {
      const names = fs.readdirSync(dir);
      if (names.some((n) => n.includes('.iteas-'))) { child.kill('SIGTERM'); caught = true; break; }
      if (names.includes('big.glb')) break;  // written before a look found the temporary file
    }
    const { code, signal } = await ended;
    if (!caught && attempt < 5) continue;
    assert.ok(caught, 'the temporary file was never seen');
    assert.equal(signal, 'SIGTERM', `exit code ${code}`);
    assert.deepEqual(fs.readdirSync(dir), []);
    return;
  }
});

// A job past the memory limit stops with one line and exit 3, writing nothing
// (without the limit, uniform level 8 of bun_zipper with no triangle budget
// grew until the kernel killed the process); a smaller job finishes under it.
// Level 5 (3.8 million triangles) needs more than 64 MiB and finishes without
// the limit, so this fails rather than exhausts the machine if it is ignored.
maybe('usage')('a job past --memory-limit stops with a message and no output', () => {
  const input = path.join(DATA, 'bunny-npm.obj');
  const out = path.join(tmp, 'memory-limit.glb');
  const r = iteas(['refine', input, '-o', out, '--mode', 'uniform', '--levels', '5', '--memory-limit', '64M']);
  assert.equal(r.code, 3, r.stderr);
  assert.match(r.stderr.trim(), /^iteas: .+bunny-npm\.obj: the job needs more memory than its limit of 64 MiB .+ \(memory_limit\)$/);
  assert.equal(r.stderr.trim().split('\n').length, 1, r.stderr);
  assert.ok(!fs.existsSync(out));
  // inspect and convert hold the input and the decoded mesh under it too.
  for (const args of [['inspect', input], ['convert', input, out]]) {
    const small = iteas([...args, '--memory-limit', '200K']);
    assert.equal(small.code, 3, small.stderr);
    assert.match(small.stderr.trim(), /^iteas: .+bunny-npm\.obj: the job needs more memory than its limit of 204800 bytes .+\(memory_limit\)$/);
    assert.ok(!fs.existsSync(out));
    assert.equal(iteas([...args, '--memory-limit', '5Q']).code, 2);
  }
  assert.equal(iteas(['inspect', input, '--memory-limit=64M']).code, 0);
  const ok = iteas(['refine', input, '-o', out, '--mode', 'uniform', '--levels', '2', '--memory-limit=64M', '--stats', '-', '--quiet']);
  assert.equal(ok.code, 0, ok.stderr);
  assert.equal(JSON.parse(ok.stdout).output.triangles, 3674 * 16);
  assert.ok(fs.existsSync(out));
});
