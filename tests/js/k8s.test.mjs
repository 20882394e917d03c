// The Kubernetes manifests under docker/k8s pass the Kubernetes OpenAPI schemas
// (kubernetes-models, no cluster needed) and agree with the server's own
// settings: probes on /readyz and /healthz, termination grace over the drain,
// the memory limit over the server's --memory-limit (issue 7, point 3).
import { test } from 'node:test';
import assert from 'node:assert/strict';
import fs from 'node:fs';
import path from 'node:path';
import YAML from 'yaml';
import { Deployment } from 'kubernetes-models/apps/v1';
import { Service, PersistentVolumeClaim } from 'kubernetes-models/v1';
import { HorizontalPodAutoscaler } from 'kubernetes-models/autoscaling/v2';
import { PodDisruptionBudget } from 'kubernetes-models/policy/v1';
import { SOURCE_DIR } from './check.mjs';

const MODELS = { Deployment, Service, PersistentVolumeClaim, HorizontalPodAutoscaler, PodDisruptionBudget };
const file = path.join(SOURCE_DIR, 'docker/k8s/iteas.yaml');
const docs = YAML.parseAllDocuments(fs.readFileSync(file, 'utf8')).map((d) => d.toJSON()).filter(Boolean);
const byKind = Object.fromEntries(docs.map((d) => [d.kind, d]));
const bytes = (q) => {
  const m = String(q).match(/^(\d+(?:\.\d+)?)(Ki|Mi|Gi|K|M|G)?$/);
  const unit = { Ki: 1024, Mi: 1024 ** 2, Gi: 1024 ** 3, K: 1024, M: 1024 ** 2, G: 1024 ** 3 }[m[2]] || 1;
  return Number(m[1]) * unit;
};

test('every manifest passes its Kubernetes schema', () => {
  assert.deepEqual(Object.keys(byKind).sort(), Object.keys(MODELS).sort());
  for (const doc of docs) {
    const Model = MODELS[doc.kind];
    assert.ok(Model, `unexpected kind ${doc.kind}`);
    assert.doesNotThrow(() => new Model(doc).validate(), `${doc.kind} is not valid`);
  }
  // The validator does catch mistakes.
  const broken = structuredClone(byKind.Deployment);
  broken.spec.replicas = 'three';
  assert.throws(() => new Deployment(broken).validate());
});

test('the Deployment matches the server: probes, drain, memory, non-root', () => {
  const pod = byKind.Deployment.spec.template.spec;
  const c = pod.containers[0];
  const env = Object.fromEntries(c.env.filter((e) => 'value' in e).map((e) => [e.name, e.value]));
  assert.equal(c.readinessProbe.httpGet.path, '/readyz');
  assert.equal(c.livenessProbe.httpGet.path, '/healthz');
  assert.ok(pod.terminationGracePeriodSeconds > Number(env.ITEAS_GRACE) + 5, 'the grace period covers the drain');
  assert.ok(bytes(env.ITEAS_MEMORY_LIMIT) < bytes(c.resources.limits.memory), 'the server bound is under the container limit');
  assert.equal(c.resources.requests.memory, c.resources.limits.memory);
  assert.ok(pod.securityContext.runAsNonRoot);
  assert.equal(env.ITEAS_HOST, '0.0.0.0');
  assert.equal(c.volumeMounts.find((v) => v.name === 'jobs').mountPath, env.ITEAS_JOB_DIR);
  assert.deepEqual(byKind.PersistentVolumeClaim.spec.accessModes, ['ReadWriteMany']);
  assert.equal(byKind.HorizontalPodAutoscaler.spec.scaleTargetRef.name, byKind.Deployment.metadata.name);
  assert.ok(byKind.PodDisruptionBudget.spec.minAvailable < byKind.HorizontalPodAutoscaler.spec.minReplicas);
});
