#!/usr/bin/env bash
# Three replicas behind nginx on loopback, a shared job store, a mixed load for
# DURATION seconds, and every replica restarted (SIGTERM drain) one at a time
# while the load runs (issue 7, point 2). Exit 0 only with 0 failed requests.
#   docker/scale-test.sh [build/iteas]      DURATION=120 CLIENTS=8
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BIN=${1:-$ROOT/build/iteas}
DURATION=${DURATION:-120}
CLIENTS=${CLIENTS:-8}
WORK=$(mktemp -d /tmp/iteas-scale-XXXXXX)
LB_PORT=${LB_PORT:-18580}
PORTS=(18581 18582 18583)
command -v nginx >/dev/null || { echo "nginx is missing (apt-get install nginx-light)" >&2; exit 2; }
mkdir -p "$WORK/jobs" "$WORK/nginx"
declare -A PID
log() { printf '[scale] %s %s\n' "$(date +%T)" "$*" >&2; }

start_replica() {
  local i=$1
  "$BIN" serve --host 127.0.0.1 --port "${PORTS[$i]}" --workers 1 --queue 32 --grace 60 \
    --job-dir "$WORK/jobs" >>"$WORK/replica$i.log" 2>&1 &
  PID[$i]=$!
  for _ in $(seq 100); do
    curl -fsS "http://127.0.0.1:${PORTS[$i]}/readyz" >/dev/null 2>&1 && return 0
    sleep 0.1
  done
  log "replica $i did not become ready"; return 1
}

# As root, nginx's workers would drop to www-data, which cannot write our temp dir.
USER_LINE=; [ "$(id -u)" != 0 ] || USER_LINE="user root;"
cat >"$WORK/nginx/nginx.conf" <<CONF
$USER_LINE
worker_processes 1;
pid $WORK/nginx/nginx.pid;
error_log $WORK/nginx/error.log warn;
events { worker_connections 1024; }
http {
  access_log $WORK/nginx/access.log;
  client_body_temp_path $WORK/nginx/body;
  proxy_temp_path $WORK/nginx/proxy;
  fastcgi_temp_path $WORK/nginx/fastcgi;
  uwsgi_temp_path $WORK/nginx/uwsgi;
  scgi_temp_path $WORK/nginx/scgi;
  upstream iteas {
    least_conn;
$(for p in "${PORTS[@]}"; do echo "    server 127.0.0.1:$p max_fails=1 fail_timeout=2s;"; done)
  }
  server {
    listen 127.0.0.1:$LB_PORT;
    client_max_body_size 256m;
    client_body_buffer_size 4m;
    location / {
      proxy_pass http://iteas;
      proxy_read_timeout 300s;
      # A draining replica answers 503 before it reads the work, a stopped one
      # refuses the connection: either way the request goes to another replica.
      proxy_next_upstream error timeout http_503 non_idempotent;
      proxy_next_upstream_tries 3;
    }
  }
}
CONF

# Stops everything; the logs stay for a failed run and go with a passed one.
cleanup() {
  local code=$?
  for i in 0 1 2; do [ -n "${PID[$i]:-}" ] && kill "${PID[$i]}" 2>/dev/null || true; done
  [ -f "$WORK/nginx/nginx.pid" ] && kill "$(cat "$WORK/nginx/nginx.pid")" 2>/dev/null || true
  wait 2>/dev/null || true
  if [ "$code" = 0 ]; then rm -rf "$WORK"; else log "failed ($code); logs kept in $WORK"; fi
}
trap cleanup EXIT

for i in 0 1 2; do start_replica "$i"; done
nginx -p "$WORK/nginx" -c "$WORK/nginx/nginx.conf"
for _ in $(seq 50); do curl -fsS "http://127.0.0.1:$LB_PORT/healthz" >/dev/null 2>&1 && break; sleep 0.1; done
log "3 replicas on ${PORTS[*]} behind nginx on $LB_PORT; load for ${DURATION}s from $CLIENTS clients"

node "$ROOT/docker/mixed-load.mjs" "http://127.0.0.1:$LB_PORT" "$DURATION" "$CLIENTS" \
  "$ROOT/tests/data/bunny-npm.obj" "$ROOT/tests/data/Box.glb" "$ROOT/tests/data/eight.off" >"$WORK/load.json" &
LOAD=$!

# Restart each replica in turn while the load runs.
STEP=$(( DURATION / 4 ))
RESTARTS=0
for i in 0 1 2; do
  sleep "$STEP"
  log "SIGTERM replica $i (pid ${PID[$i]})"
  t0=$(date +%s%N)
  kill -TERM "${PID[$i]}"
  code=0; wait "${PID[$i]}" || code=$?
  log "replica $i drained and exited $code after $(( ($(date +%s%N) - t0) / 1000000 )) ms"
  [ "$code" = 0 ] || { log "replica $i exited $code"; exit 1; }
  start_replica "$i"
  RESTARTS=$((RESTARTS + 1))
  log "replica $i back"
done

code=0; wait "$LOAD" || code=$?
cat "$WORK/load.json"
TOTAL=$(grep -c 'HTTP/1.1" [0-9]' "$WORK/nginx/access.log" || true)
FIVEXX=$(grep -cE 'HTTP/1.1" 5[0-9][0-9]' "$WORK/nginx/access.log" || true)
log "restarts: $RESTARTS; requests through nginx: $TOTAL; 5xx answered to clients: $FIVEXX; load exit $code"
log "drain lines: $(cat "$WORK"/replica*.log | grep -c draining)"
[ "$code" = 0 ] && [ "$FIVEXX" = 0 ]
