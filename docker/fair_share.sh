#!/usr/bin/env bash
# Two callers with their own keys competing for one replica on /v1/pose: a greedy one (closed
# loop, $GREEDY requests in flight) and a polite one (an open loop of $POLITE requests per
# second). The polite one first alone, then beside the greedy one; then both again with the
# per-caller queue share off (DS3D_CALLER_QUEUE_SHARE=1), batches still round-robin.
#   IMAGES=../shared/data/lsp/images docker/fair_share.sh [DURATION_S] [OUT_DIR]
# Results: OUT_DIR/{alone,polite,greedy,polite_noshare,greedy_noshare}.json (+ .png); a summary
# line per run on stdout.
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-60}
OUT=${2:-out/fair_share}
PORT=${PORT:-8766}
PY=${PY:-.venv/bin/python}
GREEDY=${GREEDY:-64}
POLITE=${POLITE:-1}
IMAGES=${IMAGES:?set IMAGES to a folder or glob of images}
GREEDY_KEY=greedy-caller-key-0123456789
POLITE_KEY=polite-caller-key-0123456789
mkdir -p "$OUT"

summary() {  # NAME: one line of OUT/NAME.json
    $PY -c "import json, sys; d = json.load(open(sys.argv[1])); l = d['latency_ms_ok'] or {}
print('%-15s ok/s=%5.2f p50=%6s p99=%6s %s' % (sys.argv[2], d['ok_rps'], *[round(l[k]) if l else None for k in ('p50', 'p99')], d['status_counts']))" "$OUT/$1.json" "$1"
}

load() {  # NAME KEY LOAD-ARGS...: one load test
    local name=$1 key=$2; shift 2
    $PY -m tools.loadtest "http://127.0.0.1:$PORT" --endpoint pose --images "$IMAGES" \
        --duration "$DURATION" --deadline 10 --api-key "$key" --out "$OUT" --name "$name" "$@" >/dev/null
}

serve() {  # EXTRA ENV...: start the service with both keys, wait until it is ready
    env DS3D_API_KEYS="$GREEDY_KEY,$POLITE_KEY" DS3D_PORT=$PORT "$@" $PY -m ds3d_service >"$OUT/server.log" 2>&1 &
    SERVER=$!
    for _ in $(seq 120); do curl -sf "http://127.0.0.1:$PORT/readyz" >/dev/null && return; sleep 1; done
    echo "the service did not start" >&2; exit 1
}
trap 'kill $SERVER 2>/dev/null || true' EXIT

serve
load alone "$POLITE_KEY" --mode open --rate "$POLITE"
load greedy "$GREEDY_KEY" --mode closed --concurrency "$GREEDY" & GREEDY_PID=$!
load polite "$POLITE_KEY" --mode open --rate "$POLITE"
wait $GREEDY_PID
kill -TERM $SERVER; wait $SERVER || true

serve DS3D_CALLER_QUEUE_SHARE=1
load greedy_noshare "$GREEDY_KEY" --mode closed --concurrency "$GREEDY" & GREEDY_PID=$!
load polite_noshare "$POLITE_KEY" --mode open --rate "$POLITE"
wait $GREEDY_PID
kill -TERM $SERVER; wait $SERVER || true

for name in alone polite greedy polite_noshare greedy_noshare; do summary $name; done
