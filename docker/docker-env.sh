# Sourced by docker/build.sh and docker/check.sh: make `docker` usable or say why it cannot be.
# ensure_docker returns 0 when a docker daemon answers, 3 when docker cannot run here at all (the
# reason in $SKIP_REASON), 1 on a real error. As root with apt it installs docker.io, docker-compose
# and debootstrap, and starts dockerd itself when no service manager runs it (its log: $DOCKERD_LOG).
DOCKERD_LOG="${DOCKERD_LOG:-/var/tmp/trackdeform-dockerd.log}"
SKIP_REASON=""
STARTED_DOCKERD=""   # the pid of the dockerd this script started (stop_started_dockerd stops it)

stop_started_dockerd() {
    [ -n "$STARTED_DOCKERD" ] || return 0
    kill -TERM "$STARTED_DOCKERD" 2>/dev/null || return 0
    local i
    for i in $(seq 30); do kill -0 "$STARTED_DOCKERD" 2>/dev/null || break; sleep 1; done
    STARTED_DOCKERD=""
}

compose() {
    if command -v docker-compose >/dev/null 2>&1; then docker-compose "$@"; else docker compose "$@"; fi
}

ensure_docker() {
    if command -v docker >/dev/null 2>&1 && docker info >/dev/null 2>&1; then
        compose version >/dev/null 2>&1 && return 0
    fi
    local need=()
    command -v dockerd >/dev/null 2>&1 || need+=(docker.io)
    { command -v docker-compose >/dev/null 2>&1 || docker compose version >/dev/null 2>&1; } || need+=(docker-compose)
    command -v debootstrap >/dev/null 2>&1 || need+=(debootstrap)
    if [ ${#need[@]} -gt 0 ]; then
        if [ "$(id -u)" != 0 ]; then SKIP_REASON="not root and ${need[*]} not installed"; return 3; fi
        if ! command -v apt-get >/dev/null 2>&1; then SKIP_REASON="no apt-get to install ${need[*]}"; return 3; fi
        echo "installing ${need[*]}"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${need[@]}" >/dev/null \
            || { echo "error: apt-get install ${need[*]} failed" >&2; return 1; }
    fi
    if ! docker info >/dev/null 2>&1; then
        if [ "$(id -u)" != 0 ]; then SKIP_REASON="no docker daemon that $(id -un) may use, and only root can start one"; return 3; fi
        echo "starting dockerd (log $DOCKERD_LOG)"
        nohup dockerd >"$DOCKERD_LOG" 2>&1 &
        STARTED_DOCKERD=$!
        local i
        for i in $(seq 60); do
            docker info >/dev/null 2>&1 && break
            if ! kill -0 "$STARTED_DOCKERD" 2>/dev/null; then
                STARTED_DOCKERD=""
                if grep -qiE 'operation not permitted|permission denied|cannot .*cgroup|iptables' "$DOCKERD_LOG"; then
                    SKIP_REASON="dockerd cannot run in this sandbox: $(grep -iE 'level=(error|fatal)' "$DOCKERD_LOG" | tail -1)"
                    return 3
                fi
                echo "error: dockerd exited; see $DOCKERD_LOG:" >&2; tail -5 "$DOCKERD_LOG" >&2; return 1
            fi
            sleep 1
        done
        docker info >/dev/null 2>&1 || { echo "error: dockerd did not answer in 60 s ($DOCKERD_LOG)" >&2; return 1; }
    fi
    return 0
}
