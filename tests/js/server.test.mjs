// Integration tests of `iteas serve`: the real binary on a loopback port
// (issue 4 points 1-4). All traffic goes to 127.0.0.1 and every loop is bounded.
import { test, before, after } from 'node:test';
import assert from 'node:assert/strict';
import { spawnSync } from 'node:child_process';
import fs from 'node:fs';
import net from 'node:net';
import path from 'node:path';
import zlib from 'node:zlib';
import Ajv2020 from 'ajv/dist/2020.js';
import { BIN, DATA, SOURCE_DIR, HAVE_CORPUS, CORPUS, tmp, listFiles, nastyMeshes, checkGltfOutput, parseGltf, startServer, stopServer, logWhen, killLeftoverServers } from './check.mjs';

// ITEAS_JS_ONLY=a,b runs only the tests named a or b.
const only = (process.env.ITEAS_JS_ONLY || '').split(',').filter(Boolean);
const maybe = (name) => (only.length && !only.includes(name) ? test.skip : test);
// ITEAS_TEST_SANITIZER=thread: the binary runs under ThreadSanitizer, 7-9 times
// slower, and the tests that need a job to outlast others size it down.
const UNDER_TSAN = process.env.ITEAS_TEST_SANITIZER === 'thread';

const ajv = new Ajv2020({ strict: false, allErrors: true });
const statsSchema = JSON.parse(fs.readFileSync(path.join(SOURCE_DIR, 'proto/stats.schema.json'), 'utf8'));
const jobSchema = JSON.parse(fs.readFileSync(path.join(SOURCE_DIR, 'proto/job.schema.json'), 'utf8'));
const errorSchema = JSON.parse(fs.readFileSync(path.join(SOURCE_DIR, 'proto/error.schema.json'), 'utf8'));
ajv.addSchema(statsSchema, 'stats.schema.json');
const validateStats = ajv.compile(statsSchema);
const validateJob = ajv.compile(jobSchema);
const validateError = ajv.compile(errorSchema);

function assertSchema(validate, value, what) {
  assert.ok(validate(value), `${what}: ${JSON.stringify(validate.errors?.slice(0, 3))}`);
}

async function expectError(res, status, code) {
  assert.equal(res.status, status, `expected ${status}, got ${res.status}`);
  const body = await res.json();
  assertSchema(validateError, body, 'error envelope');
  assert.equal(body.error.status, status);
  if (code) assert.equal(body.error.code, code);
  return body;
}

const withoutTimings = (s) => {
  const c = structuredClone(s);
  delete c.timings_ms;
  delete c.output.bytes;
  for (const l of c.levels) delete l.ms;
  return c;
};

const sleep = (ms) => new Promise((r) => setTimeout(r, ms));

let server;
before(async () => { server = await startServer(['--workers', '2', '--queue', '64', '--max-upload-bytes', String(8 << 20), '--read-timeout', '2']); });
after(async () => { if (server) await stopServer(server); killLeftoverServers(); });

const jobStatus = async (s, loc) => (await (await fetch(s.url + loc)).json()).status;
// Polls a job's status while it is |status| (at most 2 minutes); returns the next one.
async function statusAfter(s, loc, status) {
  let now = await jobStatus(s, loc);
  for (let i = 0; i < 6000 && now === status; i++) {
    await sleep(20);
    now = await jobStatus(s, loc);
  }
  return now;
}

function meshesToSend() {
  const files = listFiles(DATA);
  if (HAVE_CORPUS) for (const s of ['gltf', 'gltf-draco', 'drc', 'classic', 'classic-converted']) files.push(...listFiles(path.join(CORPUS, s)));
  return files.filter((f) => fs.statSync(f).size <= 8 << 20);
}

maybe('api')('every mesh through the sync and the job API: valid output, statistics match the schema and each other', async (t) => {
  for (const file of meshesToSend()) {
    await t.test(path.basename(file), async () => {
      const body = fs.readFileSync(file);
      const query = 'levels=2&max_triangles=300000';
      const res = await fetch(`${server.url}/v1/refine?${query}`, { method: 'POST', body, headers: { 'Content-Type': 'application/octet-stream' } });
      if (res.status === 422) {  // point clouds and the like
        await expectError(res, 422);
        return;
      }
      assert.equal(res.status, 200, await res.clone().text());
      const stats = JSON.parse(res.headers.get('x-iteas-stats'));
      assertSchema(validateStats, stats, 'statistics');
      const out = path.join(tmp, path.basename(file) + '.srv.glb');
      fs.writeFileSync(out, Buffer.from(await res.arrayBuffer()));
      const facts = await checkGltfOutput(out);
      assert.equal(facts.triangles, stats.output.triangles);
      assert.equal(facts.vertices, stats.output.vertices);
      // The same through the job API.
      const created = await fetch(`${server.url}/v1/jobs?${query}`, { method: 'POST', body, headers: { 'Content-Type': 'application/octet-stream' } });
      assert.equal(created.status, 202);
      const loc = created.headers.get('location');
      assert.match(loc, /^\/v1\/jobs\/[0-9a-f]+$/);
      assertSchema(validateJob, await created.json(), 'job');
      let status;
      for (let i = 0; i < 600; i++) {
        status = await (await fetch(server.url + loc)).json();
        assertSchema(validateJob, status, 'job');
        if (['done', 'failed', 'cancelled'].includes(status.status)) break;
        await sleep(50);
      }
      assert.equal(status.status, 'done');
      assert.deepEqual(withoutTimings(status.statistics), withoutTimings(stats));
      const result = await fetch(`${server.url}${loc}/result`);
      assert.equal(result.status, 200);
      assert.equal(Buffer.from(await result.arrayBuffer()).length, status.statistics.output.bytes);
      assert.equal((await fetch(server.url + loc, { method: 'DELETE' })).status, 200);
      assert.equal((await fetch(server.url + loc)).status, 404);
    });
  }
});

maybe('api')('a finished job is kept for the job TTL, then answers 404, and the server lives on', async () => {
  // The sweep that ends a job erased it from the job table while holding the
  // job's own lock, whose mutex the erase freed: ThreadSanitizer reported the
  // unlock as a heap use after free (the server then exits 66).
  const s = await startServer(['--workers', '1', '--job-ttl', '2']);
  try {
    const body = fs.readFileSync(path.join(DATA, 'eight.off'));
    for (let round = 0; round < 3; round++) {
      const ids = [];
      for (let i = 0; i < 3; i++) {
        const created = await fetch(`${s.url}/v1/jobs?levels=1`, { method: 'POST', body, headers: { 'Content-Type': 'application/octet-stream' } });
        assert.equal(created.status, 202);
        ids.push(created.headers.get('location'));
      }
      for (const loc of ids) {
        let state = await statusAfter(s, loc, 'queued');
        if (state === 'running') state = await statusAfter(s, loc, 'running');
        assert.equal(state, 'done');
        const result = await fetch(`${s.url}${loc}/result`);
        assert.equal(result.status, 200);
        await result.arrayBuffer();
      }
      await sleep(2300);  // past the TTL of every job of this round
      for (const loc of ids) {
        await expectError(await fetch(s.url + loc), 404, 'job_not_found');
        await expectError(await fetch(`${s.url}${loc}/result`), 404, 'job_not_found');
      }
    }
    assert.equal((await fetch(`${s.url}/healthz`)).status, 200);
  } finally {
    assert.equal(await stopServer(s), 0, 'the server exits 0');
  }
});

maybe('errors')('bad requests get their documented 4xx and envelope, and the server stays healthy', async (t) => {
  const post = (query, body, type = 'application/octet-stream') =>
    fetch(`${server.url}/v1/refine${query}`, { method: 'POST', body, headers: { 'Content-Type': type } });
  const box = fs.readFileSync(path.join(DATA, 'Box.glb'));
  // A tetrahedron as OBJ text, for requests written byte by byte.
  const tet = 'v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 1 4 3\n';
  await t.test('broken files', async () => {
    for (const file of nastyMeshes()) {
      const res = await post('', fs.readFileSync(file));
      if (res.status === 200) { assert.ok(JSON.parse(res.headers.get('x-iteas-stats')).warnings); await res.arrayBuffer(); continue; }
      assert.ok([400, 413, 415, 422].includes(res.status), `${path.basename(file)}: ${res.status}`);
      await expectError(res, res.status);
    }
  });
  await t.test('truncated and bit-flipped uploads', async () => {
    for (let n = 0; n < box.length; n += 97) {
      const res = await post('', box.subarray(0, n));
      assert.ok(res.status < 500, `prefix ${n}: ${res.status}`);
      await res.arrayBuffer();
    }
    let seed = 7;
    for (let i = 0; i < 60; i++) {
      const x = Buffer.from(box);
      for (let k = 0; k < 3; k++) { seed = (seed * 1103515245 + 12345) % 2147483648; x[seed % x.length] ^= 1 << (seed % 8); }
      const res = await post('', x);
      assert.ok(res.status < 500, `flip ${i}: ${res.status}`);
      await res.arrayBuffer();
    }
  });
  await t.test('content types, garbage, empty', async () => {
    await expectError(await post('', box, 'text/html'), 415, 'unsupported_media_type');
    await expectError(await post('', Buffer.from('garbage garbage garbage garbage')), 415);
    await expectError(await post('', Buffer.alloc(0)), 400, 'empty_body');
    await expectError(await post('', Buffer.from('{"asset": {"version": "2.0"}, "meshes": [')), 400, 'bad_json');
  });
  await t.test('bad and unknown options', async () => {
    for (const q of ['?levels=0', '?levels=abc', '?mode=loop', '?bogus=1', '?tension=1', '?threshold=p200', '?mode=fixed']) {
      const body = await expectError(await post(q, box), 400, 'bad_option');
      assert.match(body.error.message, /option '/);
    }
    // An option given twice: which value was meant is unknown (the last one was used).
    const twice = await expectError(await post('?levels=1&mode=uniform&levels=2', box), 400, 'bad_option');
    assert.match(twice.error.message, /option 'levels' is given more than once/);
  });
  await t.test('absurd declared counts', async () => {
    const gltf = JSON.stringify({ asset: { version: '2.0' }, accessors: [{ componentType: 5126, count: 2147483647, type: 'VEC3', min: [0, 0, 0], max: [1, 1, 1] }], meshes: [{ primitives: [{ attributes: { POSITION: 0 } }] }] });
    const res = await post('', Buffer.from(gltf), 'model/gltf+json');
    assert.ok([400, 413, 422].includes(res.status));
    await expectError(res, res.status);
  });
  await t.test('buffers that point outside are refused and nothing is read', async () => {
    for (const uri of ['file:///etc/passwd', '../secret.bin', '/etc/passwd', 'http://127.0.0.1:1/x']) {
      const gltf = JSON.stringify({ asset: { version: '2.0' }, buffers: [{ uri, byteLength: 36 }], bufferViews: [{ buffer: 0, byteLength: 36 }], accessors: [{ bufferView: 0, componentType: 5126, count: 3, type: 'VEC3', min: [0, 0, 0], max: [1, 1, 0] }], meshes: [{ primitives: [{ attributes: { POSITION: 0 } }] }] });
      await expectError(await post('', Buffer.from(gltf), 'model/gltf+json'), 400, 'external_uri');
    }
  });
  await t.test('an upload over the limit is refused before it is read', async () => {
    const res = await post('', Buffer.alloc((8 << 20) + 1, 1));
    assert.equal(res.status, 413);
  });
  await t.test('chunked, gzip and multipart uploads are held to the limit after decoding', async () => {
    // Debian's cpp-httplib applies the limit (8 MiB here) to a declared
    // Content-Length only: before, these were read whole (a 64 KB gzip body
    // became 64 MiB in the server) and answered 415 for what they held.
    const url = `${server.url}/v1/refine?mode=uniform&levels=1`;
    const stream = (buf) => new ReadableStream({
      start(c) {
        for (let i = 0; i < buf.length; i += 1 << 20) c.enqueue(buf.subarray(i, i + (1 << 20)));
        c.close();
      },
    });
    const chunked = (buf, headers = { 'Content-Type': 'application/octet-stream' }) =>
      fetch(url, { method: 'POST', body: stream(buf), duplex: 'half', headers });
    const bunny = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
    const refined = async (res) => {
      assert.equal(res.status, 200, res.status === 200 ? '' : await res.text());
      assert.equal(JSON.parse(res.headers.get('x-iteas-stats')).output.triangles, 14696);
      await res.arrayBuffer();
    };
    await refined(await chunked(bunny));
    await refined(await fetch(url, { method: 'POST', body: zlib.gzipSync(bunny),
      headers: { 'Content-Type': 'application/octet-stream', 'Content-Encoding': 'gzip' } }));
    // 4 MiB over (read and dropped), 40 MiB over (the rest left unread).
    await expectError(await chunked(Buffer.alloc(12 << 20, 1)), 413, 'payload_too_large');
    await expectError(await chunked(Buffer.alloc(48 << 20, 1)), 413, 'payload_too_large');
    const bomb = zlib.gzipSync(Buffer.alloc(64 << 20));
    assert.ok(bomb.length < 100 << 10, `${bomb.length} bytes`);
    await expectError(await fetch(url, { method: 'POST', body: bomb,
      headers: { 'Content-Type': 'application/octet-stream', 'Content-Encoding': 'gzip' } }), 413, 'payload_too_large');
    await expectError(await fetch(url, { method: 'POST', body: bunny.subarray(0, 5000),
      headers: { 'Content-Type': 'application/octet-stream', 'Content-Encoding': 'gzip' } }), 400, 'bad_body');
    // A multipart body sent chunked: its mesh part within the limit, then over it.
    const multipart = (mesh) => Buffer.concat([
      Buffer.from('--XyZ\r\nContent-Disposition: form-data; name="mesh"; filename="bunny.obj"\r\n' +
        'Content-Type: application/octet-stream\r\n\r\n'), mesh, Buffer.from('\r\n--XyZ--\r\n')]);
    const form = { 'Content-Type': 'multipart/form-data; boundary=XyZ' };
    await refined(await chunked(multipart(bunny), form));
    await expectError(await chunked(multipart(Buffer.alloc(12 << 20, 0x20)), form), 413, 'payload_too_large');
    // What followed the 413s on their connections was not logged as requests.
    assert.doesNotMatch(server.log(), / info \S+ {3}400 in=/);
    assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
  });
  await t.test('unknown routes and jobs', async () => {
    await expectError(await fetch(`${server.url}/v1/nope`), 404);
    await expectError(await fetch(`${server.url}/v1/jobs/abc123`), 404, 'job_not_found');
    await expectError(await fetch(`${server.url}/v1/jobs/abc123/result`), 404, 'job_not_found');
  });
  await t.test('a route asked with a method it does not take says which it takes (405, Allow)', async () => {
    const cases = [['PUT', '/v1/refine', 'POST'], ['GET', '/v1/jobs', 'POST'], ['POST', '/v1/jobs/abc12', 'GET, HEAD, DELETE'],
      ['DELETE', '/v1/jobs/abc12/result', 'GET, HEAD'], ['DELETE', '/healthz', 'GET, HEAD'], ['POST', '/metrics', 'GET, HEAD']];
    for (const [method, route, allow] of cases) {
      const res = await fetch(server.url + route, { method, body: method === 'GET' ? undefined : 'x' });
      assert.equal(res.headers.get('allow'), allow, `${method} ${route}`);
      const body = await expectError(res, 405, 'method_not_allowed');
      assert.equal(body.error.message, `${route} takes ${allow}, not ${method}`);
    }
    // No route has these paths: 404 as before.
    await expectError(await fetch(`${server.url}/v1/jobs/not-hex`, { method: 'POST', body: 'x' }), 404, 'not_found');
    await expectError(await fetch(`${server.url}/v1/refined`, { method: 'POST', body: 'x' }), 404, 'not_found');
  });
  await t.test('a method or an HTTP version the server does not know: 501, 505 (httplib said 400, malformed)', async () => {
    for (const [line, status, code] of [['FOO /healthz HTTP/1.1', 501, 'unknown_method'], ['GET /healthz HTTP/2.0', 505, 'http_version_not_supported'],
      ['GET /healthz HTTP/1.1 x', 400, 'bad_request'], ['GET /healthz HTTX/1.1', 400, 'bad_request']]) {
      const { got } = await converse(server.port, `${line}\r\nHost: x\r\n\r\n`);
      assert.match(got, new RegExp(`^HTTP/1\\.1 ${status} `), `${line}: ${got}`);
      assert.match(got, /\r\nConnection: close\r\n/i);
      const body = JSON.parse(got.slice(got.indexOf('\r\n\r\n') + 4));
      assertSchema(validateError, body, 'error envelope');
      assert.equal(body.error.code, code, line);
    }
  });
  await t.test('a request target in absolute form names the same route', async () => {
    // As a client sends it to a proxy; httplib matched the whole URL (404).
    const { got } = await converse(server.port, `GET http://127.0.0.1:${server.port}/healthz HTTP/1.1\r\nHost: x\r\n\r\n` +
      `POST HTTP://127.0.0.1/v1/refine?mode=uniform&levels=1&output=obj HTTP/1.1\r\nHost: x\r\nContent-Length: ${tet.length}\r\nConnection: close\r\n\r\n${tet}`);
    assert.deepEqual([...got.matchAll(/HTTP\/1\.1 (\d{3}) /g)].map((m) => m[1]), ['200', '200'], got);
    assert.match(got, /\{"status":"ok"\}/);
    assert.equal(got.split('\n').filter((l) => l.startsWith('f ')).length, 16, 'the tetrahedron refined once (4 × 4 faces)');
    // An upload so named takes the upload limit, not the 1 MiB of other
    // routes (the route was told from the path before it was rewritten).
    const big = tet + '# padding\n'.repeat(120000);
    const up = await converse(server.port, `POST http://127.0.0.1/v1/refine?mode=uniform&levels=1&output=obj HTTP/1.1\r\nHost: x\r\n` +
      `Content-Length: ${big.length}\r\nConnection: close\r\n\r\n${big}`);
    assert.match(up.got, /^HTTP\/1\.1 200 /, up.got.slice(0, 300));
  });
  await t.test('a request with neither Content-Length nor Transfer-Encoding has no body', async () => {
    // httplib read one until the connection closed: the POST took the GET
    // after it as its body, and both waited for a 408.
    const { got } = await converse(server.port, 'POST /v1/refine HTTP/1.1\r\nHost: x\r\n\r\n' +
      'GET /healthz HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n');
    const statuses = [...got.matchAll(/HTTP\/1\.1 (\d{3}) /g)].map((m) => m[1]);
    assert.deepEqual(statuses, ['400', '200'], got);
    assert.match(got, /"code":"empty_body"/);
  });
  await t.test('a body framed so that httplib would take it wrongly is refused, and the connection closed', async () => {
    const statuses = (got) => [...got.matchAll(/HTTP\/1\.1 (\d{3}) /g)].map((m) => m[1]);
    const next = 'GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n';
    // A length that is not a number: httplib read "abc" as 0 and parsed the
    // body as the next request (which then timed out: 400, 408).
    for (const length of ['abc', '5x', '-1', '5\r\nContent-Length: 6']) {
      const { got } = await converse(server.port, `POST /v1/refine HTTP/1.1\r\nHost: x\r\nContent-Length: ${length}\r\n\r\nhello` + next);
      assert.deepEqual(statuses(got), ['400'], `${length}: ${got}`);
      assert.match(got, /"code":"bad_content_length"/);
      assert.match(got, /\r\nConnection: close\r\n/i);
    }
    // A transfer coding other than chunked alone: httplib read the body
    // until the connection closed (a 408 after the read timeout).
    const te = await converse(server.port, 'POST /v1/refine HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: gzip, chunked\r\n\r\n5\r\nhello\r\n0\r\n\r\n' + next);
    assert.deepEqual(statuses(te.got), ['501'], te.got);
    assert.match(te.got, /"code":"unsupported_transfer_encoding"/);
    // Chunks and a length: the chunks frame the body, and the connection is
    // closed after the answer (what follows is not read as a request).
    const both = await converse(server.port, `POST /v1/refine?mode=uniform&levels=1&output=obj HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\nContent-Length: 3\r\n\r\n${tet.length.toString(16)}\r\n${tet}\r\n0\r\n\r\n` + next);
    assert.deepEqual(statuses(both.got), ['200'], both.got);
    assert.match(both.got, /\r\nConnection: close\r\n/i);
    // Header lines httplib drops (no colon, a space before it, folded) or
    // decodes (%XX: "%36%34" was taken as 64): the body's length could be
    // read differently by a proxy in front.
    const length = tet.length.toString().split('').map((c) => `%${c.charCodeAt(0).toString(16)}`).join('');
    for (const [header, fault] of [[`Content-Length : ${tet.length}`, /no space may come before its colon/],
      [`NoColon\r\nContent-Length: ${tet.length}`, /has no colon/], [`X-A: 1\r\n folded\r\nContent-Length: ${tet.length}`, /folded/],
      [`Content-Length: ${length}`, /Content-Length is percent-encoded/]]) {
      const { got } = await converse(server.port, `POST /v1/refine?mode=uniform&levels=1&output=obj HTTP/1.1\r\nHost: x\r\n${header}\r\n\r\n${tet}` + next);
      assert.deepEqual(statuses(got), ['400'], `${header}: ${got}`);
      assert.match(got, /"code":"bad_header"/);
      assert.match(got, fault);
    }
    // A request that asked to close, refused: one Connection header, not two.
    const bad = await converse(server.port, 'POST /v1/refine HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\nConnection: close\r\n\r\nzz\r\n');
    assert.deepEqual(statuses(bad.got), ['400'], bad.got);
    assert.equal(bad.got.match(/\r\nConnection: /gi).length, 1, bad.got);
    assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
  });
  await t.test('bytes that are not UTF-8 in a path, an option name or a mesh are answered, not fatal', async () => {
    // The error envelope quotes them; nlohmann::json::dump threw on them,
    // and from httplib's error handler that ended the process (found by
    // fuzz_http: one GET of a path with a byte 0xAD in it).
    const replaced = (body) => assert.ok(body.error.message.includes('\uFFFD'), body.error.message);
    replaced(await expectError(await fetch(`${server.url}/v1/nope%AD%C3`), 404, 'not_found'));
    const raw = await converse(server.port, Buffer.concat([Buffer.from('GET /v1/jobs/0123/resul'), Buffer.from([0xad]),
      Buffer.from(' HTTP/1.1\r\nHost: x\r\nConnection: close\r\n\r\n')]));
    assert.match(raw.got, /^HTTP\/1\.1 404 /);
    replaced(JSON.parse(Buffer.from(raw.got.slice(raw.got.indexOf('\r\n\r\n') + 4), 'latin1').toString('utf8')));
    assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
    replaced(await expectError(await post('?%AD=1', box), 400, 'bad_option'));
    // A reader's message quotes a malformed token.
    const obj = Buffer.concat([Buffer.from('v 0 0 0\nv 1 0 0\nv '), Buffer.from([0xad, 0xc3]), Buffer.from(' 1 0\nf 1 2 3\n')]);
    replaced(await expectError(await post('', obj), 400, 'bad_obj'));
    const queued = await fetch(`${server.url}/v1/jobs`, { method: 'POST', body: obj });
    assert.equal(queued.status, 202);
    const loc = queued.headers.get('location');
    await queued.arrayBuffer();
    let status;
    for (let i = 0; i < 200; i++) {
      const res = await fetch(server.url + loc);
      assert.equal(res.status, 200);
      status = await res.json();
      if (status.status !== 'queued' && status.status !== 'running') break;
      await sleep(25);
    }
    assertSchema(validateJob, status, 'job status');
    assert.equal(status.status, 'failed');
    assert.ok(status.error.message.includes('\uFFFD'), status.error.message);
    assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
  });
  await t.test('a client that disconnects mid-upload, and one that stalls (slowloris)', async () => {
    // A connection held |keepOpenMs|, then closed by us; |dropped| counts
    // those the server gave up on first (an answer, or its end of the
    // connection closed), |answers| what it said to them.
    let dropped = 0;
    const answers = [];
    const raw = (payload, keepOpenMs) => new Promise((resolve) => {
      let ours = false;
      let given = false;
      const answer = answers.push('') - 1;
      const gaveUp = () => { if (!ours && !given) { given = true; ++dropped; } };
      const sock = net.connect(server.port, '127.0.0.1', () => {
        sock.write(payload);
        setTimeout(() => { ours = true; sock.destroy(); resolve(); }, keepOpenMs);
      });
      sock.on('data', (d) => { gaveUp(); answers[answer] += d.toString('latin1'); });
      sock.on('end', gaveUp);
      sock.on('error', () => resolve());
    });
    const header = `POST /v1/refine HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/octet-stream\r\nContent-Length: ${box.length}\r\n\r\n`;
    await raw(header + box.subarray(0, 100).toString('latin1'), 10);  // disconnect mid-upload
    // Twenty stalled connections that never finish their headers. The health
    // check is answered while they still hold their connections, not once the
    // read timeout (2 s here) has dropped them: an order, not a time limit.
    const stalled = Array.from({ length: 20 }, () => raw('POST /v1/refine HTTP/1.1\r\nHost: x\r\n', 3000));
    await sleep(200);
    assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
    assert.equal(dropped, 0, 'served while stalled clients hold connections');
    await Promise.all(stalled);
    assert.equal(dropped, 20, 'the read timeout drops a stalled connection');
    // Each gets a 408 of its own, with a request id, and "Connection: close".
    assert.equal(answers.length, 21);
    assert.equal(answers[0], '', 'no answer to a client gone mid-upload');
    for (const a of answers.slice(1)) {
      assert.match(a, /^HTTP\/1\.1 408 /);
      assert.match(a, /\r\nConnection: close\r\n/i);
      assert.match(a, /\r\nX-Request-Id: [0-9a-f]{20}\r\n/i);
      assert.match(a, /"code":"request_timeout","message":"the request line and headers were not all sent within 2 s"/);
    }
    assert.equal(new Set(answers.slice(1).map((a) => a.match(/X-Request-Id: (\w+)/i)[1])).size, 20);
  });
  assert.equal((await fetch(`${server.url}/healthz`)).status, 200);
  assert.equal((await fetch(`${server.url}/readyz`)).status, 200);
  const metrics = await (await fetch(`${server.url}/metrics`)).text();
  assert.match(metrics, /iteas_requests_total\{route="\/v1\/refine",status="400"\}/);
  assert.match(metrics, /iteas_request_duration_seconds_bucket/);
  assert.match(metrics, /iteas_queue_depth \d+/);
});

maybe('auth')('what a client sends cannot forge access-log lines or fields', async () => {
  // A decoded %0A in the path wrote a line of the client's own into the text
  // log; a quote in X-Request-Id wrote fields into a JSON log line.
  for (const format of ['text', 'json']) {
    const s = await startServer(['--workers', '1', '--log-format', format]);
    try {
      await (await fetch(`${s.url}/v1/jobs/abc%0A2026-11-27%2000:00:00.000%20info%20FORGED%0A`)).arrayBuffer();
      const forged = await fetch(`${s.url}/healthz`, { headers: { 'X-Request-Id': 'x","level":"critical","forged":"1' } });
      assert.match(forged.headers.get('x-request-id'), /^[0-9a-f]{20}$/);
      const kept = await fetch(`${s.url}/healthz`, { headers: { 'X-Request-Id': '0f8fad5b-d9cb-469f-a165-70867728950e' } });
      assert.equal(kept.headers.get('x-request-id'), '0f8fad5b-d9cb-469f-a165-70867728950e');
      // Listening, and one line a request, in whatever order the request
      // threads wrote them.
      const log = await logWhen(s, (l) => l.trim().split('\n').length >= 4);
      await sleep(100);
      assert.equal(s.log(), log, 'no line after the three requests\'');
      const lines = log.trim().split('\n');
      assert.equal(lines.length, 4, log);
      assert.ok(!lines.some((l) => /^FORGED|^2026-11-27 00:00/.test(l)), log);
      assert.doesNotMatch(log, /forged|critical/);
      assert.equal(lines.filter((l) => /0f8fad5b-d9cb-469f-a165-70867728950e/.test(l)).length, 1, log);
      if (format === 'json') for (const l of lines) assert.equal(typeof JSON.parse(l), 'object', l);
      else assert.ok(lines.some((l) => /GET \/v1\/jobs\/abc%0A2026-11-27%2000:00:00.000%20info%20FORGED%0A 404/.test(l)), log);
    } finally { assert.equal(await stopServer(s), 0); }
  }
});

maybe('errors')('Range only on GET; requests answered before routing get their own id, code and log line', async () => {
  const s = await startServer(['--workers', '1', '--log-format', 'json', '--read-timeout', '1']);
  try {
    const box = fs.readFileSync(path.join(DATA, 'Box.glb'));
    // A POST ignores Range: the whole refined mesh (it was a 206 slice).
    const posted = await fetch(`${s.url}/v1/refine?compression=none`, { method: 'POST', body: box, headers: { 'Content-Type': 'model/gltf-binary', Range: 'bytes=0-99' } });
    assert.equal(posted.status, 200);
    const glb = Buffer.from(await posted.arrayBuffer());
    assert.equal(glb.length, JSON.parse(posted.headers.get('x-iteas-stats')).output.bytes);
    assert.equal(glb.readUInt32LE(8), glb.length);
    // An error is whole; a GET's answer is sliced as asked.
    await expectError(await fetch(`${s.url}/v1/nope`, { headers: { Range: 'bytes=0-5' } }), 404, 'not_found');
    const part = await fetch(`${s.url}/healthz`, { headers: { Range: 'bytes=0-3' } });
    assert.equal(part.status, 206);
    assert.equal((await part.text()).length, 4);
    // Answered before routing.
    const ids = [];
    const early = async (res, status, code) => {
      ids.push(res.headers.get('x-request-id'));
      assert.match(ids.at(-1) ?? '', /^[0-9a-f]{20}$/);
      assert.equal(res.headers.get('connection'), 'close');
      await expectError(res, status, code);
    };
    await early(await fetch(`${s.url}/${'a'.repeat(9000)}`), 414, 'uri_too_long');
    for (const [payload, status, code] of [['G"ET / HTTP/1.1\r\nHost: x\r\n\r\n', 400, 'bad_request'],
      ['POST /v1/refine HTTP/1.1\r\nHost: x\r\n', 408, 'request_timeout']]) {  // headers never ended
      const answer = (await converse(s.port, payload)).got;
      assert.match(answer, new RegExp(`^HTTP/1\\.1 ${status} `));
      assert.match(answer, new RegExp(`"code":"${code}"`));
      ids.push(answer.match(/\r\nX-Request-Id: ([0-9a-f]{20})\r\n/i)?.[1]);
    }
    // One JSON line a request; the early ones under their own ids, with no
    // duration (their start is not known) and no method httplib did not parse.
    const log = await logWhen(s, (l) => ids.every((id) => l.includes(id)));
    const lines = log.trim().split('\n').map((l) => JSON.parse(l));
    const access = lines.filter((l) => l.request_id);
    assert.equal(access.length, 6, log);
    assert.equal(new Set(access.map((l) => l.request_id)).size, 6);
    for (const id of ids) {
      const line = access.find((l) => l.request_id === id);
      assert.ok(line, `${id} logged: ${log}`);
      assert.equal(line.ms, null);
    }
    // (By id: a line is written after its answer, so two may come in either order.)
    assert.deepEqual(ids.map((id) => access.find((l) => l.request_id === id)).map((l) => [l.status, l.method]),
      [[414, '-'], [400, '-'], [408, 'POST']]);
    for (const l of access.filter((a) => !ids.includes(a.request_id))) assert.equal(typeof l.ms, 'number');
    const metrics = await (await fetch(`${s.url}/metrics`)).text();
    assert.match(metrics, /^iteas_requests_total\{route="other",status="414"\} 1$/m);
    assert.match(metrics, /^iteas_request_duration_seconds_count\{route="\/v1\/refine"\} 1$/m, 'the unread POST has no duration');
  } finally { assert.equal(await stopServer(s), 0); }
});

maybe('errors')('Range as RFC 9110 has it: GET alone, fitted to the answer, 416 with its length; any other ignored', async () => {
  const s = await startServer(['--workers', '1']);
  try {
    const whole = await (await fetch(`${s.url}/healthz`)).text();
    const n = whole.length;
    const get = (range, route = '/healthz') => fetch(`${s.url}${route}`, { headers: { Range: range } });
    for (const [range, from, to] of [['bytes=0-3', 0, 3], ['bytes=2-99999', 2, n - 1], ['bytes=-4', n - 4, n - 1],
      ['bytes=-99', 0, n - 1], ['bytes=3-', 3, n - 1], ['bytes=0-1, 99-100', 0, 1]]) {
      const res = await get(range);
      assert.equal(res.status, 206, range);
      assert.equal(res.headers.get('content-range'), `bytes ${from}-${to}/${n}`, range);
      assert.equal(await res.text(), whole.slice(from, to + 1), range);
    }
    const parts = await get('bytes=0-1,4-5');
    assert.equal(parts.status, 206);
    assert.match(parts.headers.get('content-type'), /^multipart\/byteranges; boundary=/);
    assert.match(await parts.text(), new RegExp(`Content-Range: bytes 4-5/${n}\r\n\r\n${whole.slice(4, 6)}`));
    // No range within the answer: 416 with the answer's length.
    for (const range of [`bytes=${n}-`, 'bytes=-0', `bytes=${n}-${n + 5}`]) {
      const res = await get(range);
      assert.equal(res.headers.get('content-range'), `bytes */${n}`, range);
      await expectError(res, 416, 'range_not_satisfiable');
    }
    // A unit the server does not know, a malformed range, or one on another
    // method: ignored, the answer whole (httplib answered 416 before any
    // handler, and a POST lost its upload).
    for (const range of ['pages=1', 'bytes=5-2', 'bytes=abc', 'bytes=-', 'bytes=0-99999999999999999999']) {
      const res = await get(range);
      assert.equal(res.status, 200, range);
      assert.equal(res.headers.get('content-range'), null, range);
      assert.equal(await res.text(), whole, range);
    }
    const head = await fetch(`${s.url}/healthz`, { method: 'HEAD', headers: { Range: 'bytes=0-3' } });
    assert.equal(head.status, 200);
    assert.equal(head.headers.get('content-length'), String(n));
    const spec = await (await fetch(`${s.url}/v1/openapi.yaml`)).text();
    const tail = await get('bytes=-100', '/v1/openapi.yaml');
    assert.equal(tail.status, 206);
    assert.equal(await tail.text(), spec.slice(-100));
    // Ranges that ask for more than the answer (httplib built each part: 2,700
    // copies of "0-" made a 708 KB result a 1.9 GB answer), or more than 16
    // of them: the whole answer. Up to 16 disjoint ones are served.
    const bytes = (k) => Array.from({ length: k }, (_, i) => `${2 * i}-${2 * i}`).join(',');
    for (const range of [`bytes=0-${',0-'.repeat(2700)}`, 'bytes=0-,0-', `bytes=${bytes(17)}`]) {
      const res = await get(range, '/v1/openapi.yaml');
      assert.equal(res.status, 200, range.slice(0, 20));
      assert.equal(await res.text(), spec, range.slice(0, 20));
    }
    const sixteen = await get(`bytes=${bytes(16)}`, '/v1/openapi.yaml');
    assert.equal(sixteen.status, 206);
    assert.equal((await sixteen.text()).match(/\r\nContent-Range: bytes \d+-\d+\//g).length, 16);
    // The web page's files are fitted alike (httplib sliced them itself).
    const page = Buffer.from(await (await fetch(`${s.url}/`)).arrayBuffer());
    assert.match(page.toString(), /<html/i);
    const first = await get('bytes=10-99999999', '/');
    assert.equal(first.status, 206);
    assert.equal(first.headers.get('content-range'), `bytes 10-${page.length - 1}/${page.length}`);
    assert.deepEqual(Buffer.from(await first.arrayBuffer()), page.subarray(10));
    const two = await get('bytes=0-1,4-5', '/');
    assert.equal(two.status, 206);
    assert.match(two.headers.get('content-type'), /^multipart\/byteranges; boundary=/);
    const several = await get('bytes=0-,0-', '/');
    assert.equal(several.status, 200);
    assert.deepEqual(Buffer.from(await several.arrayBuffer()), page);
    const past = await get(`bytes=${page.length}-`, '/');
    assert.equal(past.headers.get('content-range'), `bytes */${page.length}`);
    await expectError(past, 416, 'range_not_satisfiable');
    assert.equal((await fetch(`${s.url}/`, { headers: { Range: 'pages=1' } })).status, 200);
    // An upload with a Range header httplib could not parse is refined; its
    // body, which has a line that begins "Range:", reaches the reader as it
    // was sent (a byte added there would push out the last face's last).
    const obj = Buffer.from('v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nv 0 0 1\r\nf 1 3 2\r\nf 1 2 4\r\nf 1 4 3\r\nRange: bytes=0-3\r\nf 2 3 4');
    for (const range of ['pages=1', 'bytes=0-9']) {
      const posted = await fetch(`${s.url}/v1/refine?compression=none`, { method: 'POST', body: obj, headers: { Range: range, 'Content-Type': 'model/obj' } });
      assert.equal(posted.status, 200, range);
      const input = JSON.parse(posted.headers.get('x-iteas-stats')).input;
      assert.deepEqual([input.bytes, input.vertices, input.triangles], [obj.length, 4, 4], range);
    }
    // On the wire: the header's name in any case; two Range headers are
    // ignored; each request of a pipelined pair has its own; a space before
    // the colon is refused, so the name the server hands httplib a Range
    // header under (a space before its colon) cannot come from a client.
    const raw = async (headers) => (await converse(s.port, `GET /healthz HTTP/1.1\r\nHost: x\r\n${headers}Connection: close\r\n\r\n`)).got;
    const mixed = await raw('rAnGe: bytes=0-3\r\n');
    assert.ok(mixed.startsWith('HTTP/1.1 206 ') && mixed.endsWith(`\r\n\r\n${whole.slice(0, 4)}`), mixed);
    assert.match(await raw('Range: bytes=0-3\r\nRange: bytes=4-5\r\n'), /^HTTP\/1\.1 200 /);
    assert.match(await raw('Range : bytes=0-3\r\n'), /^HTTP\/1\.1 400 [^]*"code":"bad_header"/);
    const pair = (await converse(s.port, 'GET /healthz HTTP/1.1\r\nHost: x\r\nRange: bytes=0-3\r\n\r\n' +
      'GET /healthz HTTP/1.1\r\nHost: x\r\nRange: bytes=4-5\r\nConnection: close\r\n\r\n')).got;
    assert.deepEqual([...pair.matchAll(/Content-Range: (\S+ \S+)/gi)].map((m) => m[1]), [`bytes 0-3/${n}`, `bytes 4-5/${n}`]);
  } finally { assert.equal(await stopServer(s), 0); }
});

// Sends |head| on a new connection, then |more| (each string or Buffer)
// every |everyMs| until the server answers and closes, or |giveUpMs|:
// resolves with what came back, and whether we were still sending.
function converse(port, head, { more = [], everyMs = 200, giveUpMs = 10000 } = {}) {
  return new Promise((resolve) => {
    const sock = net.connect(port, '127.0.0.1');
    let got = '';
    let sending = true;
    let timer;
    const done = () => { clearInterval(timer); sending = false; sock.destroy(); };
    sock.on('connect', () => {
      sock.write(head);
      let i = 0;
      timer = setInterval(() => { if (sending && i < more.length) sock.write(more[i++]); }, everyMs);
    });
    sock.on('data', (d) => { got += d.toString('latin1'); });
    sock.on('error', () => {});
    sock.on('close', () => { const answeredWhileSending = sending; done(); resolve({ got, answeredWhileSending }); });
    setTimeout(() => { if (sending) { sending = false; done(); } }, giveUpMs);
  });
}
const peakKiB = (pid) => Number(fs.readFileSync(`/proc/${pid}/status`, 'utf8').match(/VmHWM:\s+(\d+)/)[1]);

maybe('errors')('a connection is bounded: its head in time and size, a body a route takes no upload on, a slow body', async () => {
  const s = await startServer(['--workers', '1', '--read-timeout', '1', '--min-rate', '100000', '--http-threads', '4']);
  try {
    const status = (got) => Number(got.match(/^HTTP\/1\.1 (\d{3})/)?.[1]);
    const code = (got) => got.match(/"code":"(\w+)"/)?.[1];
    // Four connections sending a header line every 200 ms, never ending the
    // head (all four connection threads): each is answered 408 while it still
    // sends (it held its thread for as long as it went on), and the server
    // answers again.
    const trickled = await Promise.all(Array.from({ length: 4 }, () =>
      converse(s.port, 'GET /healthz HTTP/1.1\r\nHost: x\r\n', { more: Array(50).fill('X-A: b\r\n') })));
    for (const t of trickled) {
      assert.ok(t.answeredWhileSending, t.got);
      assert.equal(status(t.got), 408, t.got);
      assert.equal(code(t.got), 'request_timeout');
    }
    assert.equal((await fetch(`${s.url}/healthz`)).status, 200);
    // A 64 MB request line: 414 without holding it (a 300 MB one took the
    // server to 600 MB; the bound leaves room for the sanitizers' own
    // memory); 10,000 header lines (90 KB): 431.
    const before = peakKiB(s.proc.pid);
    const longLine = await converse(s.port, Buffer.concat([Buffer.from('GET /'), Buffer.alloc(64 << 20, 97)]));
    assert.equal(status(longLine.got), 414, longLine.got.slice(0, 200));
    assert.ok(peakKiB(s.proc.pid) - before < 32 << 10, `peak ${before} -> ${peakKiB(s.proc.pid)} KiB`);
    const flood = await converse(s.port, `GET /healthz HTTP/1.1\r\nHost: x\r\n${'X-A: b\r\n'.repeat(10000)}\r\n`);
    assert.equal(status(flood.got), 431, flood.got.slice(0, 200));
    assert.equal(code(flood.got), 'headers_too_large');
    // A body on a route that takes no upload: 1 MiB at most off the wire
    // (httplib read it whole: 200 MB chunked took 338 MB), none encoded (it
    // was decoded whole: 872 KB of gzip became 200 MB).
    const chunk = Buffer.alloc(1 << 20, 0);
    const put = await converse(s.port, 'PUT /v1/refine HTTP/1.1\r\nHost: x\r\nTransfer-Encoding: chunked\r\n\r\n',
      { more: Array(8).fill(Buffer.concat([Buffer.from('100000\r\n'), chunk, Buffer.from('\r\n')])), everyMs: 20 });
    assert.equal(status(put.got), 413, put.got.slice(0, 300));
    assert.match(put.got, /PUT \/v1\/refine takes no body over 1024 KiB/);
    const gz = zlib.gzipSync(Buffer.alloc(8 << 20, 0));
    const del = await converse(s.port, Buffer.concat([Buffer.from(`DELETE /v1/jobs/abc HTTP/1.1\r\nHost: x\r\nContent-Encoding: gzip\r\nContent-Length: ${gz.length}\r\n\r\n`), gz]));
    assert.equal(status(del.got), 415, del.got.slice(0, 300));
    assert.equal(code(del.got), 'unsupported_encoding');
    // An upload at 5 KB/s against --min-rate 100000: 408 once the read
    // timeout has passed, while it still sends.
    const slow = await converse(s.port, 'POST /v1/refine HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nContent-Length: 100000\r\n\r\n',
      { more: Array(100).fill(Buffer.alloc(1000, 32)) });
    assert.ok(slow.answeredWhileSending, slow.got);
    assert.equal(status(slow.got), 408, slow.got.slice(0, 300));
    assert.match(slow.got, /the body came slower than 100000 bytes a second/);
    // A client that asks first (Expect: 100-continue, as curl does past 1 MB)
    // with a length over the limit is told 413 at once, and sends nothing
    // (it got "100 Continue", sent it all and was told then); under the
    // limit it is asked to go on.
    const box = fs.readFileSync(path.join(DATA, 'Box.glb'));
    const asks = (length, more) => converse(s.port, `POST /v1/refine HTTP/1.1\r\nHost: x\r\nContent-Type: model/gltf-binary\r\nExpect: 100-continue\r\nConnection: close\r\nContent-Length: ${length}\r\n\r\n`, { more });
    const huge = await asks(1e12, []);
    assert.match(huge.got, /^HTTP\/1\.1 413 /, huge.got.slice(0, 200));
    assert.equal(code(huge.got), 'payload_too_large');
    const fits = await asks(box.length, [box]);
    assert.match(fits.got, /^HTTP\/1\.1 100 Continue\r\n\r\nHTTP\/1\.1 200 /, fits.got.slice(0, 200));
    // And the server still serves.
    assert.equal((await fetch(`${s.url}/v1/refine`, { method: 'POST', body: box, headers: { 'Content-Type': 'model/gltf-binary' } })).status, 200);
  } finally { assert.equal(await stopServer(s), 0); }
});

maybe('slowread')('a client reading slower than --min-rate has its response cut off, and the log says so', async () => {
  const s = await startServer(['--workers', '1', '--read-timeout', '1', '--min-rate', '10000000']);
  try {
    const bunny = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
    // 17 MB back, more than the sockets' buffers hold; the client reads
    // nothing until the server has given up on it (its log line), then all.
    const sock = net.connect(s.port, '127.0.0.1');
    let got = Buffer.alloc(0);
    const closed = new Promise((resolve) => sock.on('close', resolve));
    sock.on('data', (d) => { got = Buffer.concat([got, d]); });
    sock.on('error', () => {});
    sock.write(`POST /v1/refine?mode=uniform&levels=4&compression=none HTTP/1.1\r\nHost: x\r\nContent-Type: application/octet-stream\r\nContent-Length: ${bunny.length}\r\n\r\n`);
    sock.write(bunny);
    sock.pause();
    const log = await logWhen(s, (l) => / cut-off$/m.test(l), 60000);
    assert.match(log, /POST \/v1\/refine 200 in=110437 out=\d+ [\d.]+ms 127\.0\.0\.1 cut-off$/m);
    sock.resume();
    await closed;
    const length = Number(got.toString('latin1').match(/\r\nContent-Length: (\d+)\r\n/i)[1]);
    const head = got.indexOf('\r\n\r\n') + 4;
    assert.ok(length > 16e6);
    assert.ok(got.length - head < length, `${got.length - head} of ${length} bytes`);
    // A client that reads gets it all on the same server.
    const whole = await fetch(`${s.url}/v1/refine?mode=uniform&levels=4&compression=none`, { method: 'POST', body: bunny, headers: { 'Content-Type': 'application/octet-stream' } });
    assert.equal((await whole.arrayBuffer()).byteLength, Number(whole.headers.get('content-length')));  // (timings in its statistics: a few bytes more or less)
    const refined = (await logWhen(s, (l) => (l.match(/POST \/v1\/refine 200/g) || []).length === 2))
      .split('\n').filter((l) => / POST \/v1\/refine 200 /.test(l));
    assert.equal(refined.length, 2);
    assert.doesNotMatch(refined[1], /cut-off/);
  } finally { assert.equal(await stopServer(s), 0); }
});

maybe('errors')('a port in use is refused, not shared; error lines of the JSON log are JSON', async () => {
  const a = await startServer(['--workers', '1']);
  try {
    // httplib's default socket options took SO_REUSEPORT: a second server
    // on the port started, and the kernel split the connections between them.
    const second = spawnSync(BIN, ['serve', '--port', String(a.port), '--log-format', 'json'], { encoding: 'utf8', timeout: 10000 });
    assert.equal(second.status, 4, second.stdout + second.stderr);
    assert.deepEqual({ ...JSON.parse(second.stdout.trim()), time: undefined },
      { time: undefined, level: 'error', event: 'listen_failed', host: '127.0.0.1', port: a.port });
  } finally { assert.equal(await stopServer(a), 0); }
  // These lines were free text inside the JSON object's braces.
  const notDir = spawnSync(BIN, ['serve', '--port', '0', '--log-format', 'json', '--job-dir', path.join(DATA, 'Box.glb')], { encoding: 'utf8', timeout: 10000 });
  assert.equal(notDir.status, 2, notDir.stdout + notDir.stderr);
  const line = JSON.parse(notDir.stdout.trim());
  assert.equal(line.event, 'job_store_unusable');
  assert.match(line.message, /Box\.glb is not a directory/);
  // In the text log, such a line stays one line whatever it quotes.
  const odd = path.join(tmp, 'a\n2026-11-27 00:00:00.000 info forged');
  fs.writeFileSync(odd, '');
  const text = spawnSync(BIN, ['serve', '--port', '0', '--job-dir', odd], { encoding: 'utf8', timeout: 10000 });
  assert.equal(text.status, 2, text.stdout + text.stderr);
  assert.equal(text.stdout.trim().split('\n').length, 1, text.stdout);
  assert.match(text.stdout, /a\\x0A2026-11-27 00:00:00\.000 info forged is not a directory/);
});

maybe('auth')('an API key is required when configured', async () => {
  const s = await startServer(['--workers', '1'], { ITEAS_API_KEY: 'sekret' });
  try {
    const box = fs.readFileSync(path.join(DATA, 'Box.glb'));
    await expectError(await fetch(`${s.url}/v1/refine`, { method: 'POST', body: box }), 401, 'unauthorized');
    await expectError(await fetch(`${s.url}/v1/refine`, { method: 'POST', body: box, headers: { Authorization: 'Bearer wrong' } }), 401);
    const ok = await fetch(`${s.url}/v1/refine`, { method: 'POST', body: box, headers: { Authorization: 'Bearer sekret', 'Content-Type': 'model/gltf-binary' } });
    assert.equal(ok.status, 200);
    assert.equal((await fetch(`${s.url}/healthz`)).status, 200);
    // A refused upload must not leave its body on a keep-alive connection:
    // two requests on one socket, the first unauthorised, the second not;
    // with a declared length, and chunked (3 MB, which the server reads and
    // drops after its 401; left unread, it was parsed as requests, 400 each).
    const big = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
    for (const [body, chunked] of [[box, false], [Buffer.concat(Array(28).fill(big)), true]]) {
      const twoRequests = await new Promise((resolve, reject) => {
        const sock = net.connect(s.port, '127.0.0.1');
        let got = '';
        const framing = chunked ? 'Transfer-Encoding: chunked' : `Content-Length: ${body.length}`;
        const payload = chunked
          ? Buffer.concat([Buffer.from(body.length.toString(16) + '\r\n'), body, Buffer.from('\r\n0\r\n\r\n')]) : body;
        const req = (auth) => Buffer.concat([Buffer.from(`POST /v1/refine HTTP/1.1\r\nHost: x\r\n${auth}Content-Type: application/octet-stream\r\n${framing}\r\n\r\n`, 'latin1'), payload]);
        let sent = 1;
        sock.on('data', (d) => {
          got += d.toString('latin1');
          const n = (got.match(/HTTP\/1\.1 /g) || []).length;
          if (n >= 2) { sock.destroy(); resolve(got); }
          else if (n === 1 && sent === 1 && got.includes('"status":401}')) { sent = 2; sock.write(req('Authorization: Bearer sekret\r\n')); }
        });
        sock.on('error', reject);
        setTimeout(() => { sock.destroy(); resolve(got); }, 20000);
        sock.write(req(''));
      });
      const statuses = [...twoRequests.matchAll(/HTTP\/1\.1 (\d{3})/g)].map((m) => Number(m[1]));
      assert.deepEqual(statuses, [401, 200], `chunked: ${chunked}`);
    }
    assert.doesNotMatch(s.log(), / info \S+ {3}400 in=/);
  } finally { assert.equal(await stopServer(s), 0); }
});

// httplib 0.11 listens with a backlog of 5: 200 connections opened at once
// lost 32-33 to resets in two rounds of three, and the load benchmark lost
// requests to ECONNRESET. The server now listens again with a backlog of
// 1,024 (GuardedServer::raise_listen_backlog).
maybe('backpressure')('a burst of 300 connections at once is answered on every one, none reset', async () => {
  // The kernel caps a backlog at net.core.somaxconn (4,096 since Linux 5.4,
  // 128 before): the burst stays within half of it.
  let somaxconn = 4096;
  try { somaxconn = Number(fs.readFileSync('/proc/sys/net/core/somaxconn', 'utf8')) || somaxconn; } catch {}
  const burst = Math.min(300, Math.floor(somaxconn / 2));
  const s = await startServer();
  try {
    const one = async () => {
      const { got } = await converse(s.port, 'GET /healthz HTTP/1.1\r\nHost: t\r\nConnection: close\r\n\r\n');
      return got.startsWith('HTTP/1.1 200') ? 'ok' : got ? `answer ${JSON.stringify(got.slice(0, 40))}` : 'no answer (reset)';
    };
    for (let round = 0; round < 3; round++) {
      const outcomes = await Promise.all(Array.from({ length: burst }, one));
      const tally = {};
      for (const o of outcomes) tally[o] = (tally[o] || 0) + 1;
      assert.deepEqual(tally, { ok: burst }, `round ${round}: ${JSON.stringify(tally)}`);
    }
  } finally { assert.equal(await stopServer(s), 0); }
});

maybe('backpressure')('a full queue answers 429 with Retry-After; SIGTERM drains and exits 0', async () => {
  const s = await startServer(['--workers', '1', '--queue', '1', '--grace', '20']);
  const bunny = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const send = () => fetch(`${s.url}/v1/jobs?mode=uniform&levels=4&compression=none`, { method: 'POST', body: bunny, headers: { 'Content-Type': 'application/octet-stream' } });
  const responses = [];
  for (let i = 0; i < 6; i++) responses.push(await send());
  const codes = responses.map((r) => r.status);
  assert.ok(codes.includes(202));
  const busy = responses.find((r) => r.status === 429);
  assert.ok(busy, `codes ${codes}`);
  assert.ok(Number(busy.headers.get('retry-after')) > 0);
  await expectError(busy, 429, 'queue_full');
  // SIGTERM while a job runs: readyz turns 503, the running job finishes, exit 0,
  // and a synchronous request in flight gets a whole response, never a cut one.
  const running = responses.find((r) => r.status === 202);
  const loc = running.headers.get('location');
  const exited = new Promise((resolve) => s.proc.on('exit', (code) => resolve(code)));
  const s2 = await startServer(['--workers', '1', '--grace', '20']);
  const inflight = fetch(`${s2.url}/v1/refine?mode=uniform&levels=4&compression=none`, { method: 'POST', body: bunny, headers: { 'Content-Type': 'application/octet-stream' } });
  // In flight means being refined, not still in the listen backlog (a loaded
  // machine under ThreadSanitizer can take longer than any fixed sleep); the
  // SIGTERM goes once the job runs, or at once if the response came first.
  let settled = false;
  inflight.finally(() => { settled = true; }).catch(() => {});
  for (let i = 0; i < 600 && !settled; i++) {
    const m = await fetch(`${s2.url}/metrics`).then((r) => r.text());
    if (/iteas_jobs_running [1-9]/.test(m)) break;
    await sleep(50);
  }
  const exited2 = new Promise((resolve) => s2.proc.on('exit', (code) => resolve(code)));
  s2.proc.kill('SIGTERM');
  const done = await inflight;
  const bytes = Buffer.from(await done.arrayBuffer());
  if (done.status === 200) {
    const stats = JSON.parse(done.headers.get('x-iteas-stats'));
    assert.equal(bytes.length, stats.output.bytes, 'the whole mesh arrived');
    assert.equal(bytes.readUInt32LE(8), bytes.length, 'GLB length field matches');
  } else {
    assertSchema(validateError, JSON.parse(bytes.toString('utf8')), 'error envelope');
  }
  assert.equal(await exited2, 0);
  s.proc.kill('SIGTERM');
  await sleep(100);
  const ready = await fetch(`${s.url}/readyz`).catch(() => null);
  if (ready) assert.equal(ready.status, 503);
  const status = await fetch(s.url + loc).then((r) => r.json()).catch(() => null);
  if (status) assert.ok(['running', 'done', 'queued'].includes(status.status));
  assert.equal(await exited, 0);
  assert.match(s.log(), /draining/);
});

maybe('replicas')('replicas sharing a job store: a job one reports done has its result on the other at once', async () => {
  // The scale test's race, on loopback: a client polls replica A until the
  // job is done and fetches the result through replica B, which knows the job
  // only from the shared store. A reports "done" only once the store has it.
  // A's store writes are slowed (as on a network volume) so that a gap
  // between the two would be seen, not just possible.
  const dir = fs.mkdtempSync(path.join(tmp, 'jobs-'));
  const a = await startServer(['--workers', '2', '--queue', '64', '--job-dir', dir], { ITEAS_TEST_STORE_DELAY_MS: '30' });
  const b = await startServer(['--workers', '1', '--job-dir', dir]);
  const mesh = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  try {
    for (let i = 0; i < 12; i++) {
      const sub = await fetch(`${a.url}/v1/jobs?mode=uniform&levels=${2 + (i % 2)}&compression=none`,
        { method: 'POST', body: mesh, headers: { 'Content-Type': 'application/octet-stream' } });
      assert.equal(sub.status, 202);
      const loc = sub.headers.get('location');
      let state = '';
      for (let k = 0; k < 20000 && state !== 'done'; k++) {
        state = (await (await fetch(a.url + loc)).json()).status;
        assert.ok(['queued', 'running', 'done'].includes(state), state);
      }
      assert.equal(state, 'done');
      const res = await fetch(`${b.url}${loc}/result`);
      assert.equal(res.status, 200, `job ${i}: ${res.status} ${res.status === 200 ? '' : await res.text()}`);
      assert.equal(Buffer.from(await res.arrayBuffer()).subarray(0, 4).toString(), 'glTF');
    }
  } finally {
    await stopServer(a);
    await stopServer(b);
  }
});

maybe('replicas')('a job queued longer than the TTL stays in the shared store while its replica holds it, and goes a TTL after it ends', async () => {
  // One worker on A and eight level-5 jobs (more than half a second each):
  // the last waits in the queue for seconds, against a TTL of one second.
  // The sweep went by file age alone, and took its status: B answered 404.
  // Under ThreadSanitizer a job runs 7-9 times slower (bunny-npm through the
  // CLI: level 3 1.17 s against 0.16 s, level 4 4.58 s against 0.51 s), and
  // level 3 keeps the queue long enough there.
  const level = UNDER_TSAN ? 3 : 5;
  const dir = fs.mkdtempSync(path.join(tmp, 'jobs-ttl-'));
  const a = await startServer(['--workers', '1', '--lone-job-threads', '1', '--job-dir', dir, '--job-ttl', '1']);
  const b = await startServer(['--workers', '1', '--job-dir', dir, '--job-ttl', '1']);
  const mesh = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const submit = async (server, query) => {
    const sub = await fetch(`${server.url}/v1/jobs?${query}`, { method: 'POST', body: mesh, headers: { 'Content-Type': 'application/octet-stream' } });
    assert.equal(sub.status, 202);
    return sub.headers.get('location');
  };
  const state = async (server, loc) => {
    const r = await fetch(server.url + loc);
    return r.status === 200 ? (await r.json()).status : r.status;
  };
  const until = async (server, loc, wanted) => {
    for (let k = 0; k < 6000; k++) {
      const st = await state(server, loc);
      if (wanted(st)) return st;
      await sleep(10);
    }
    assert.fail(`${loc}: never ${wanted}`);
  };
  const file = (loc, ext) => path.join(dir, loc.split('/').pop() + ext);
  try {
    const jobs = [];
    for (let i = 0; i < 8; i++) jobs.push(await submit(a, `mode=uniform&levels=${level}`));
    // Once a sweep has taken the first job's status (written when it ended,
    // after the last job's was written when it was queued), the last job,
    // still queued, is known to B.
    await until(a, jobs[0], (st) => st === 'done');
    for (let k = 0; k < 6000 && fs.existsSync(file(jobs[0], '.json')); k++) await sleep(10);
    assert.ok(!fs.existsSync(file(jobs[0], '.json')), 'a sweep took the first job');
    assert.equal(await state(a, jobs[7]), 'queued');
    assert.equal(await state(b, jobs[7]), 'queued', 'B still knows the queued job');
    await until(a, jobs[7], (st) => st === 'done');
    // Ended, it goes a TTL later, from every replica.
    assert.equal(await until(b, jobs[7], (st) => st === 404), 404);
    assert.deepEqual(fs.readdirSync(dir).filter((f) => f.startsWith(jobs[7].split('/').pop())), []);
  } finally {
    await stopServer(a);
    await stopServer(b);
  }
});

maybe('replicas')('a job store that cannot take a result: the replica that ran the job answers, the others say why', async () => {
  // Replica A writes under a 200 KiB file size limit (as a full volume
  // would refuse): an uncompressed level-2 result (about 1 MB) cannot be
  // stored, a Draco level-1 one (about 30 KB) can.
  const dir = fs.mkdtempSync(path.join(tmp, 'jobs-full-'));
  const a = await startServer(['--workers', '1', '--job-dir', dir], {}, { fileSizeKiB: 200 });
  const b = await startServer(['--workers', '1', '--job-dir', dir]);
  const mesh = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const run = async (query) => {
    const sub = await fetch(`${a.url}/v1/jobs?${query}`,
      { method: 'POST', body: mesh, headers: { 'Content-Type': 'application/octet-stream' } });
    assert.equal(sub.status, 202);
    const loc = sub.headers.get('location');
    let state = 'queued';
    for (let k = 0; k < 6000 && ['queued', 'running'].includes(state); k++) {
      await sleep(20);
      state = (await (await fetch(a.url + loc)).json()).status;
    }
    assert.equal(state, 'done');
    return loc;
  };
  try {
    const big = await run('mode=uniform&levels=2&compression=none');
    const own = await fetch(`${a.url}${big}/result`);
    assert.equal(own.status, 200);
    assert.ok((await own.arrayBuffer()).byteLength > 200 * 1024);
    assert.equal((await (await fetch(b.url + big)).json()).status, 'done');
    const other = await fetch(`${b.url}${big}/result`);
    const body = await expectError(other, 503, 'result_unavailable');
    assert.match(body.error.message, /File too large/);
    assert.equal(other.headers.get('retry-after'), '1');
    assert.match(await (await fetch(`${a.url}/metrics`)).text(), /^iteas_job_store_errors_total 1$/m);
    assert.match(await logWhen(a, (l) => /job store could not take it/.test(l)), /job store could not take it: cannot write .*File too large/);
    assert.deepEqual(fs.readdirSync(dir).filter((f) => f.includes('.tmp')), []);
    const small = await run('mode=uniform&levels=1');
    const stored = await fetch(`${b.url}${small}/result`);
    assert.equal(stored.status, 200, await stored.clone().text());
    assert.equal(Buffer.from(await stored.arrayBuffer()).subarray(0, 4).toString(), 'glTF');
    // Deleted through A: the other replica no longer finds it.
    assert.equal((await fetch(a.url + small, { method: 'DELETE' })).status, 200);
    await expectError(await fetch(`${b.url}${small}/result`), 404, 'job_not_found');
  } finally {
    assert.equal(await stopServer(a), 0);
    await stopServer(b);
  }
});

maybe('openapi')('the OpenAPI document passes a standard linter and is served', async () => {
  const lint = spawnSync(path.join(path.dirname(new URL(import.meta.url).pathname), 'node_modules/.bin/redocly'),
    ['lint', '--config', path.join(SOURCE_DIR, 'proto/redocly.yaml'), path.join(SOURCE_DIR, 'proto/openapi.yaml')], { encoding: 'utf8' });
  assert.equal(lint.status, 0, lint.stdout + lint.stderr);
  const served = await (await fetch(`${server.url}/v1/openapi.yaml`)).text();
  assert.equal(served, fs.readFileSync(path.join(SOURCE_DIR, 'proto/openapi.yaml'), 'utf8'));
});

// --- freed memory and threads: what /metrics and a job's status say ---------------
const metricsText = async (s) => (await fetch(`${s.url}/metrics`)).text();

async function trims(s) {
  const m = (await metricsText(s)).match(/^iteas_heap_trims_total (\d+)$/m);
  assert.ok(m, 'iteas_heap_trims_total in /metrics');
  return Number(m[1]);
}

// Polls the trim count until it reaches |want| (the worker trims after it has
// answered) or 20 s pass; returns the last count.
async function trimsReaching(s, want) {
  let n = await trims(s);
  for (let waited = 0; n < want && waited < 20000; waited += 25) {
    await sleep(25);
    n = await trims(s);
  }
  return n;
}

maybe('trim')('freed memory goes back after every job, once the server is idle, or not while jobs follow one another', async () => {
  const body = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const refine = async (s) => {
    const r = await fetch(`${s.url}/v1/refine?mode=uniform&levels=2`, { method: 'POST', body, headers: { 'Content-Type': 'application/octet-stream' } });
    assert.equal(r.status, 200);
    await r.arrayBuffer();
  };
  // No delay: after every job.
  const every = await startServer(['--workers', '1', '--trim-delay', '0']);
  try {
    for (let i = 0; i < 3; ++i) await refine(every);
    assert.equal(await trimsReaching(every, 3), 3);
  } finally {
    assert.equal(await stopServer(every), 0);
  }
  // An hour's delay: the jobs reuse what the ones before them freed (a few MiB
  // held, under the 256 MiB that would go back at once).
  const kept = await startServer(['--workers', '2', '--trim-delay', '3600000']);
  try {
    for (let i = 0; i < 3; ++i) await refine(kept);
    assert.equal(await trims(kept), 0);
  } finally {
    assert.equal(await stopServer(kept), 0);
  }
  // 200 ms: once the server has been idle that long, and once for the idle spell.
  const idle = await startServer(['--workers', '2', '--trim-delay', '200']);
  try {
    await refine(idle);
    assert.equal(await trimsReaching(idle, 1), 1);
    await sleep(600);
    assert.equal(await trims(idle), 1, 'one trim an idle spell');
    await refine(idle);
    assert.equal(await trimsReaching(idle, 2), 2, 'and one after the next job');
  } finally {
    assert.equal(await stopServer(idle), 0);
  }
});

async function startedByThreads(s) {
  const out = {};
  for (const m of (await metricsText(s)).matchAll(/^iteas_jobs_started_total\{threads="(\d+)"\} (\d+)$/gm)) out[m[1]] = Number(m[2]);
  return out;
}

maybe('threads')('a job gets the cores no other job holds or could take, and the same mesh on any of them', async () => {
  const bunny = fs.readFileSync(path.join(DATA, 'bunny-npm.obj'));
  const post = (s, route, query) => fetch(`${s.url}${route}?${query}`, { method: 'POST', body: bunny, headers: { 'Content-Type': 'application/octet-stream' } });
  // A long job (3.8 million triangles, Draco-encoded: seconds), running.
  // Under ThreadSanitizer (7-9 times slower, see the replicas' TTL test) level
  // 4's 940,544 triangles keep it running long enough: at level 5 the test
  // took 47 s there, at level 4 13 s.
  const longLevels = UNDER_TSAN ? 4 : 5;
  const startLong = async (s) => {
    const r = await post(s, '/v1/jobs', `mode=uniform&levels=${longLevels}`);
    assert.equal(r.status, 202);
    const loc = r.headers.get('location');
    assert.equal(await statusAfter(s, loc, 'queued'), 'running');
    return loc;
  };
  const s = await startServer(['--workers', '2', '--lone-job-threads', '2']);
  try {
    const long = await startLong(s);  // alone: two threads
    // Beside it: one thread.
    const beside = await post(s, '/v1/refine', 'levels=3');
    assert.equal(beside.status, 200);
    const besideBytes = Buffer.from(await beside.arrayBuffer());
    assert.equal(await jobStatus(s, long), 'running', 'the long job outlasted the other');
    assert.equal(await statusAfter(s, long, 'running'), 'done');
    // Alone again: two threads, the same mesh (the statistics in asset.extras
    // carry timings: the rest must match).
    const alone = await post(s, '/v1/refine', 'levels=3');
    assert.equal(alone.status, 200);
    const a = parseGltf(Buffer.from(await alone.arrayBuffer())), b = parseGltf(besideBytes);
    delete a.json.asset.extras;
    delete b.json.asset.extras;
    assert.deepEqual(a.json, b.json);
    assert.ok(a.buffers[0].equals(b.buffers[0]), 'one thread and two give the same mesh');
    assert.deepEqual(await startedByThreads(s), { 1: 1, 2: 2 });
  } finally {
    assert.equal(await stopServer(s), 0);
  }
  // One worker: jobs waiting behind the running one could not start anyway,
  // so each keeps both cores, backlog or not (two jobs queued while the long
  // one runs: the first of them starts with the other still waiting).
  const one = await startServer(['--workers', '1', '--lone-job-threads', '2']);
  try {
    const long = await startLong(one);
    const locs = [];
    for (let i = 0; i < 2; i++) {
      const r = await post(one, '/v1/jobs', 'levels=2');
      assert.equal(r.status, 202);
      locs.push(r.headers.get('location'));
    }
    assert.equal(await jobStatus(one, long), 'running', 'both queued behind the long job');
    for (const loc of [long, ...locs]) {
      let state = await statusAfter(one, loc, 'queued');
      if (state === 'running') state = await statusAfter(one, loc, 'running');
      assert.equal(state, 'done');
    }
    assert.deepEqual(await startedByThreads(one), { 2: 3 });
  } finally {
    assert.equal(await stopServer(one), 0);
  }
});

// --- resource bounds (hardening issue, point 3) -------------------------------
function rssKiB(pid) {
  const m = fs.readFileSync(`/proc/${pid}/status`, 'utf8').match(/VmRSS:\s+(\d+)/);
  return m ? Number(m[1]) : 0;
}

maybe('bounds')('bombs and oversized work get a prompt 413 or a budget stop; peak RSS stays under the memory limit with 32 at once', async () => {
  // The ~1M-triangle mesh: bunny-npm refined uniformly to level 4 (940,544 triangles), Draco GLB.
  const big = path.join(tmp, 'one-million.glb');
  const gen = spawnSync(BIN, ['refine', path.join(DATA, 'bunny-npm.obj'), '-o', big, '--mode', 'uniform', '--levels', '4',
    '--stats', big + '.json'], { encoding: 'utf8' });
  assert.equal(gen.status, 0, gen.stderr);
  const generated = JSON.parse(fs.readFileSync(big + '.json', 'utf8'));
  assert.ok(generated.output.triangles > 900000, `big mesh has ${generated.output.triangles} triangles`);
  const ply = Buffer.from('ply\nformat binary_little_endian 1.0\nelement vertex 2147483648\nproperty float x\nproperty float y\n' +
    'property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n');
  const gltf = Buffer.from(JSON.stringify({ asset: { version: '2.0' }, buffers: [{ byteLength: 12, uri: 'data:application/octet-stream;base64,AAAAAAAAAAAAAAAA' }],
    bufferViews: [{ buffer: 0, byteLength: 12 }], accessors: [{ bufferView: 0, componentType: 5126, count: 2147483648, type: 'VEC3' }],
    meshes: [{ primitives: [{ attributes: { POSITION: 0 } }] }] }));

  const limitMiB = 3072;
  // A queue of 6: at most 8 of the 32 are taken, the rest get 429 (a queue of 16 made the same
  // checks take three times as long).
  const s = await startServer(['--workers', '2', '--queue', '6', '--memory-limit', `${limitMiB}M`, '--max-output-triangles', '3000000']);
  let peak = 0;
  const counts = {};  // status -> answers of the 32
  const sampler = setInterval(() => { peak = Math.max(peak, rssKiB(s.proc.pid)); }, 50);
  try {
    const post = (body, type, query = '') => fetch(`${s.url}/v1/refine${query}`, { method: 'POST', headers: { 'Content-Type': type }, body });
    for (const name of ['crash-draco-bomb-246-bytes.drc', 'crash-draco-edgebreaker-bomb.drc']) {
      const r = await post(fs.readFileSync(path.join(DATA, 'nasty', name)), 'application/octet-stream');
      const body = await expectError(r, 413, 'decompression_bomb');
      assert.match(body.error.message, /MiB/);
    }
    await expectError(await post(ply, 'application/ply'), 413, 'too_large');
    const g = await post(gltf, 'model/gltf+json');
    assert.ok([400, 413, 422].includes(g.status), `2^31-vertex glTF answered ${g.status}`);

    // 32 requests for 8 levels at once: each one runs to its triangle budget, waits its turn for
    // memory, or is turned away with 429; never a 5xx, never an out-of-memory kill. (Without the
    // geometric tolerances, which would stop the refinement of this smooth mesh long before.)
    const bytes = fs.readFileSync(big);
    // A transport error (a reused keep-alive socket closed under a loaded CI machine) is
    // retried once, as any client would; it is counted and printed, and the server must
    // still be healthy and exit 0 at the end.
    let retries = 0;
    const once = () => post(bytes, 'model/gltf-binary', '?levels=8&tolerance=off&flat_limit=off')
      .then(async (r) => ({ status: r.status, stats: r.headers.get('x-iteas-stats'), body: await r.arrayBuffer() }));
    const answers = await Promise.all(Array.from({ length: 32 }, () => once().catch((e) => {
      ++retries;
      console.log(`# bounds: retrying after ${e.cause?.code || ''} ${e.cause?.message || e.message}`);
      return once();
    })));
    for (const a of answers) counts[a.status] = (counts[a.status] || 0) + 1;
    for (const status of Object.keys(counts)) assert.ok(['200', '429'].includes(status), `statuses ${JSON.stringify(counts)}`);
    assert.ok(counts[200] >= 1, `statuses ${JSON.stringify(counts)}`);
    for (const a of answers.filter((x) => x.status === 200)) {
      const st = JSON.parse(a.stats);
      assert.equal(st.stopped_by, 'budget');
      assert.ok(st.output.triangles <= 3000000);
    }
    assert.equal((await fetch(`${s.url}/healthz`)).status, 200);
  } finally {
    clearInterval(sampler);
    assert.equal(await stopServer(s), 0, 'the server drains and exits 0');
  }
  console.log(`# bounds: ${JSON.stringify(counts)}; peak RSS ${(peak / 1024).toFixed(0)} MiB under a ${limitMiB} MiB limit`);
  assert.ok(peak > 0 && peak < limitMiB * 1024, `peak RSS ${peak} KiB`);
});
