#!/usr/bin/env bash
# Builds the IteAS image here, runs it, and sends it real meshes (issue 7, point 1).
# Starts its own Docker engine when none runs (and stops it again), makes the
# Debian base image with debootstrap when it is missing (no registry needed).
#   docker/build.sh            build, run, check, report the image size
#   KEEP_ENGINE=1 docker/build.sh   leave the engine it started running
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
IMAGE=${IMAGE:-iteas:local}
BASE_IMAGE=${BASE_IMAGE:-local/debian:bookworm}
PORT=${PORT:-18480}
WORK=${WORK:-/var/tmp/iteas-docker}
SUDO=; [ "$(id -u)" = 0 ] || SUDO=sudo
mkdir -p "$WORK"
log() { printf '[docker/build] %s\n' "$*" >&2; }

# --- the engine ----------------------------------------------------------------
command -v dockerd >/dev/null || { log "installing docker.io"; $SUDO apt-get install -y -q docker.io >/dev/null; }
STARTED_PID=
if ! docker info >/dev/null 2>&1; then
  log "starting dockerd (iptables off; overlay2)"
  $SUDO dockerd --iptables=false --ip-masq=false --bridge=none --data-root "$WORK/engine" \
    --exec-root "$WORK/exec" --pidfile "$WORK/dockerd.pid" >"$WORK/dockerd.log" 2>&1 &
  STARTED_PID=$!
  for _ in $(seq 60); do docker info >/dev/null 2>&1 && break; sleep 1; done
  docker info >/dev/null 2>&1 || { log "dockerd did not start:"; tail -20 "$WORK/dockerd.log" >&2; exit 1; }
fi
CONTAINER=
cleanup() {
  [ -n "$CONTAINER" ] && docker rm -f "$CONTAINER" >/dev/null 2>&1 || true
  if [ -n "$STARTED_PID" ] && [ -z "${KEEP_ENGINE:-}" ]; then
    log "stopping the dockerd it started (pid $STARTED_PID)"
    $SUDO kill "$STARTED_PID" 2>/dev/null || true
    wait "$STARTED_PID" 2>/dev/null || true
  fi
}
trap cleanup EXIT

# --- a Debian base without a registry -------------------------------------------
if ! docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
  command -v debootstrap >/dev/null || $SUDO apt-get install -y -q debootstrap >/dev/null
  # The machine's own Debian mirror: the URIs of deb822 sources and the
  # one-line "deb" entries, never a comment (a missing file is no error).
  MIRROR=$( { grep -hE '^URIs:' /etc/apt/sources.list.d/*.sources 2>/dev/null | awk '{print $2}';
              grep -hE '^deb ' /etc/apt/sources.list /etc/apt/sources.list.d/*.list 2>/dev/null | awk '{print $2}'; } \
            | grep -m1 -E '/debian/?$' || true)
  MIRROR=${MIRROR:-http://deb.debian.org/debian}
  log "debootstrap minbase bookworm from $MIRROR"
  rm -rf "$WORK/rootfs"
  $SUDO debootstrap --variant=minbase bookworm "$WORK/rootfs" "$MIRROR" >"$WORK/debootstrap.log" 2>&1
  $SUDO rm -rf "$WORK/rootfs/var/cache/apt/archives/"*.deb "$WORK/rootfs/var/lib/apt/lists/"*
  $SUDO tar -C "$WORK/rootfs" -c . | docker import - "$BASE_IMAGE" >/dev/null
fi

# --- the web page's vendored three.js (the image build has no npm) --------------
if [ ! -d "$ROOT/web/node_modules/three" ]; then
  log "npm ci in web/"
  (cd "$ROOT/web" && npm ci --no-audit --no-fund --loglevel=error)
fi

# --- build ----------------------------------------------------------------------------
log "building $IMAGE from $BASE_IMAGE"
T0=$(date +%s)
docker build --network host --build-arg BASE="$BASE_IMAGE" -f "$ROOT/docker/Dockerfile" -t "$IMAGE" "$ROOT" >"$WORK/build.log" 2>&1 \
  || { tail -40 "$WORK/build.log" >&2; exit 1; }
log "built in $(( $(date +%s) - T0 )) s"
SIZE=$(docker image inspect --format '{{.Size}}' "$IMAGE")
BASE_SIZE=$(docker image inspect --format '{{.Size}}' "$BASE_IMAGE")

# --- run and check ------------------------------------------------------------------
CONTAINER=$(docker run -d --network host -e ITEAS_PORT="$PORT" -e ITEAS_WORKERS=2 "$IMAGE")
for _ in $(seq 50); do curl -fsS "http://127.0.0.1:$PORT/healthz" >/dev/null 2>&1 && break; sleep 0.2; done
HEALTH=$(curl -fsS "http://127.0.0.1:$PORT/healthz")
USER_ID=$(docker exec "$CONTAINER" id -u)
[ "$USER_ID" != 0 ] || { log "the container runs as root"; exit 1; }
MESH=${MESH:-$ROOT/tests/data/bunny-npm.obj}
STATS=$(curl -fsS -D - -o "$WORK/refined.glb" -H 'Content-Type: model/obj' --data-binary @"$MESH" \
  "http://127.0.0.1:$PORT/v1/refine" | tr -d '\r' | sed -n 's/^[Xx]-[Ii]te[Aa][Ss]-[Ss]tats: //p')
TRIS_IN=$(printf '%s' "$STATS" | node -e 'let s="";process.stdin.on("data",d=>s+=d).on("end",()=>{const j=JSON.parse(s);console.log(j.input.triangles+" -> "+j.output.triangles)})')
GLB_BYTES=$(stat -c %s "$WORK/refined.glb")
PAGE=$(curl -fsS -o /dev/null -w '%{http_code}' "http://127.0.0.1:$PORT/")
THREE=$(curl -fsS -o /dev/null -w '%{http_code} %{size_download}' "http://127.0.0.1:$PORT/vendor/three/build/three.module.js")
[ "$(head -c 4 "$WORK/refined.glb")" = glTF ] || { log "the answer is not a GLB"; exit 1; }
# The HEALTHCHECK itself, as Docker runs it.
for _ in $(seq 40); do
  H=$(docker inspect --format '{{.State.Health.Status}}' "$CONTAINER"); [ "$H" = starting ] || break; sleep 0.5
done
docker stop -t 30 "$CONTAINER" >/dev/null
EXIT=$(docker inspect --format '{{.State.ExitCode}}' "$CONTAINER")

cat <<REPORT
image            $IMAGE (base $BASE_IMAGE)
runtime image    $((SIZE / 1000000)) MB (base alone $((BASE_SIZE / 1000000)) MB; target < 200 MB)
user             uid $USER_ID (non-root)
/healthz         $HEALTH
HEALTHCHECK      $H
refine           $(basename "$MESH"): $TRIS_IN triangles, $GLB_BYTES bytes of GLB
web page         / $PAGE, three.module.js $THREE bytes
stop (SIGTERM)   exit code $EXIT
REPORT
[ "$H" = healthy ] && [ "$EXIT" = 0 ] && [ "$SIZE" -lt 200000000 ] && [ "$PAGE" = 200 ]
