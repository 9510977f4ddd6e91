#!/usr/bin/env bash
# Load-test matrix on this machine: for each batch size (the endpoint's: DS3D_MAX_BATCH_SIZE for
# pose, DS3D_MAX_LIFT_BATCH_SIZE for lift), start the service on the bundled model, run
# closed-loop tests at several concurrencies, stop it.
#   docker/loadtest_matrix.sh [DURATION_S] [OUT_DIR]
#   ENDPOINT=pose IMAGES=../shared/data/lsp/images docker/loadtest_matrix.sh   # real images
#   (IMAGES: a folder of images, or a quoted glob such as '../photos/*.jpg'; for lift, POSES=FILE
#   in `ds3d lift`'s input format, default LSP's annotations written to OUT_DIR/lsp_poses.json)
# Results: OUT_DIR/{ENDPOINT}_closed_c{N}_b{B}.json (+ .png); summary lines on stdout.
set -euo pipefail
cd "$(dirname "$0")/.."
DURATION=${1:-20}
OUT=${2:-out/loadtest}
PORT=${PORT:-8765}
PY=${PY:-.venv/bin/python}
ENDPOINT=${ENDPOINT:-lift}
mkdir -p "$OUT"
if [ "$ENDPOINT" = pose ]; then
    INPUT_ARGS=(--images "${IMAGES:?set IMAGES to a folder or glob of images}")
else  # LSP's 2000 annotated poses, or POSES=FILE in `ds3d lift`'s input format
    POSES=${POSES:-$OUT/lsp_poses.json}
    [ -f "$POSES" ] || $PY -c 'import json, sys; from ds3d.data.lsp import load_lsp; a = load_lsp()
json.dump({"joints_2d": a.joints.tolist(), "visible": a.visible.tolist()}, open(sys.argv[1], "w"))' "$POSES"
    INPUT_ARGS=(--poses "$POSES" --items "${ITEMS:-1}")  # ITEMS: poses per /v1/lift request
fi
export OMP_NUM_THREADS=1

for B in ${BATCH_SIZES:-1 16}; do
    mkdir -p "$OUT"
    if [ "$ENDPOINT" = pose ]; then BATCH_VAR=DS3D_MAX_BATCH_SIZE; else BATCH_VAR=DS3D_MAX_LIFT_BATCH_SIZE; fi
    env "$BATCH_VAR=$B" DS3D_PORT=$PORT $PY -m ds3d_service >"$OUT/server_b$B.log" 2>&1 &
    SERVER=$!
    trap 'kill $SERVER 2>/dev/null || true' EXIT
    for _ in $(seq 120); do
        curl -sf "http://127.0.0.1:$PORT/readyz" >/dev/null && break
        sleep 1
    done
    for C in ${CONCURRENCIES:-1 4 16 64}; do
        $PY -m tools.loadtest "http://127.0.0.1:$PORT" --endpoint "$ENDPOINT" "${INPUT_ARGS[@]}" \
            --mode closed --concurrency "$C" --duration "$DURATION" --out "$OUT" \
            --name "${ENDPOINT}_closed_c${C}_b${B}" --deadline 10 \
            | $PY -c "import json,sys; d=json.load(sys.stdin); l=d['latency_ms_ok'] or {}; \
print('$ENDPOINT b=$B c=$C ok/s=%.2f p50=%s p95=%s p99=%s mean_batch=%.1f %s' % (d['ok_rps'], \
*[round(l[k]) if l else None for k in ('p50','p95','p99')], d['server_mean_batch_size'] or 0, d['status_counts']))"
    done
    kill -TERM $SERVER
    wait $SERVER || true
done
