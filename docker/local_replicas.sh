#!/usr/bin/env bash
# Replicas of the service behind nginx on this host, as docker/docker-compose.yml runs them, for
# hosts without a Docker engine (nginx from the distribution: Debian `apt-get install nginx`;
# NGINX_BIN names another binary):
#   docker/local_replicas.sh [RUN_DIR]        stop with Ctrl-C or SIGTERM (stops everything)
# nginx on 127.0.0.1:$PORT (default 8080) with docker/nginx.conf's upstream and proxy settings;
# a replica (`python -m ds3d_service`) on each of $REPLICAS (default "8001 8002"), restarted when it
# dies, as compose's `restart: unless-stopped`. Extra service flags: SERVE_ARGS="--model-dir X".
# RUN_DIR (default out/replicas): the nginx config made here, the logs, replica-PORT.pid (the
# live process of each replica: `kill -9 $(cat RUN_DIR/replica-8001.pid)` to crash one).
set -euo pipefail
cd "$(dirname "$0")/.."
RUN=${1:-out/replicas}
PORT=${PORT:-8080}
REPLICAS=${REPLICAS:-"8001 8002"}
PY=${PY:-.venv/bin/python}
NGINX_BIN=${NGINX_BIN:-$(command -v nginx || echo /usr/sbin/nginx)}
# One process of one model thread per replica, as a replica of docker-compose.yml sizes itself
# from its one CPU: replicas share this host's cores.
export DS3D_WORKERS=${DS3D_WORKERS:-1} DS3D_TORCH_THREADS=${DS3D_TORCH_THREADS:-1}
export OMP_NUM_THREADS=${OMP_NUM_THREADS:-1}
mkdir -p "$RUN/tmp"
RUN=$(realpath "$RUN")
chmod 1777 "$RUN/tmp"  # nginx's workers (user nobody under root) buffer request bodies here
rm -f "$RUN/stopping"

# docker/nginx.conf with the replicas' addresses, the local port, and files under RUN_DIR.
servers=""
for p in $REPLICAS; do servers+="server 127.0.0.1:$p max_fails=0; "; done
sed -e "s|server ds3d:8000 max_fails=0;|$servers|" \
    -e "s|listen 8080;|listen 127.0.0.1:$PORT;|" \
    -e "s|access_log /dev/stdout;|access_log $RUN/nginx-access.log;|" \
    -e "s|error_log /dev/stderr warn;|error_log $RUN/nginx-error.log warn;|" \
    -e "s|^http {|http {\n    client_body_temp_path $RUN/tmp/body;\n    proxy_temp_path $RUN/tmp/proxy;\n    fastcgi_temp_path $RUN/tmp/fastcgi;\n    uwsgi_temp_path $RUN/tmp/uwsgi;\n    scgi_temp_path $RUN/tmp/scgi;|" \
    docker/nginx.conf > "$RUN/nginx.conf"

supervise() {  # one replica, restarted whenever it exits until we stop
    local port=$1
    while [ ! -f "$RUN/stopping" ]; do
        # shellcheck disable=SC2086  # SERVE_ARGS is a list of flags
        $PY -m ds3d_service --host 127.0.0.1 --port "$port" ${SERVE_ARGS:-} >>"$RUN/replica-$port.log" 2>&1 &
        echo $! >"$RUN/replica-$port.pid"
        wait $! || echo "$(date +%T) replica $port exited ($?); restarting" >>"$RUN/events.log"
        sleep 0.5
    done
}

stop() {
    touch "$RUN/stopping"
    for p in $REPLICAS; do kill -TERM "$(cat "$RUN/replica-$p.pid")" 2>/dev/null || true; done
    kill -QUIT "$(cat "$RUN/nginx.pid" 2>/dev/null)" 2>/dev/null || true
    wait
}
trap stop EXIT
trap 'exit 0' INT TERM

for p in $REPLICAS; do supervise "$p" & done
"$NGINX_BIN" -p "$RUN" -e "$RUN/nginx-error.log" -c "$RUN/nginx.conf" -g "daemon off; pid $RUN/nginx.pid;" &
wait
