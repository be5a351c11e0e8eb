#!/usr/bin/env bash
# make docker-check: build the images, run router + daemon + worker on the mock config for 30 s of real
# time, check that episodes were written with live keypoints and that an outside subscriber saw them,
# then tear down (containers, network; the images stay cached). Prints "skipped: <reason>" and exits 0
# where docker cannot run at all (no root, no apt); any build or run error fails.
set -euo pipefail
cd "$(dirname "$0")/.."
. docker/docker-env.sh
SECONDS_RUN="${DOCKER_CHECK_SECONDS:-30}"
export TRACKDEFORM_IMAGE="${TRACKDEFORM_IMAGE:-trackdeform3d:latest}"
T0=$(date +%s)

rc=0; ensure_docker || rc=$?
if [ "$rc" = 3 ]; then echo "docker-check skipped: $SKIP_REASON"; exit 0; elif [ "$rc" != 0 ]; then exit 1; fi
trap stop_started_dockerd EXIT
docker/build.sh
T_BUILD=$(date +%s)

project="tdcheck$$"
run=docker/run/$project
mkdir -p "$run/data"
export TRACKDEFORM_CONFIG="$PWD/$run/station.yaml" TRACKDEFORM_DATA="$PWD/$run/data"
export TRACKDEFORM_ROUTER_PUBLISH="127.0.0.1:"   # a free host port: never the 7447 of a session on this host
dc() { compose -p "$project" -f docker/compose.yaml "$@"; }
ok=0
teardown() {
    dc logs --no-color > "$run/compose.log" 2>&1 || true
    dc down --remove-orphans -t 10 >/dev/null 2>&1 || true
    if [ "$ok" = 1 ]; then rm -rf "$run"; else echo "docker-check: logs and data kept in $run" >&2; fi
    stop_started_dockerd   # a dockerd this check started does not outlive it
}
trap teardown EXIT

# The mock station as zenoh clients of the router (the topology docker/compose.yaml documents).
docker run --rm -i --entrypoint python "$TRACKDEFORM_IMAGE" -c '
import sys, yaml
d = yaml.safe_load(sys.stdin)
d["bus"].update(mode="client", listen=[], connect=["tcp/router:7447"])
d["output"]["min_free_gb"] = 0.5
yaml.safe_dump(d, sys.stdout, sort_keys=False)' < configs/mock.yaml > "$TRACKDEFORM_CONFIG"

dc up -d router worker
dc up -d daemon
T_UP=$(date +%s)
# An outside subscriber in its own container, through the router only.
dc run --rm -T --no-deps worker watch --config /config/station.yaml --seconds $((SECONDS_RUN + 10)) \
    > "$run/watch.log" 2> "$run/watch.err" &
watch_pid=$!
sleep "$SECONDS_RUN"
daemon_id=$(dc ps -q daemon)
t_stop0=$(date +%s.%N)
dc stop -t 60 daemon >/dev/null
t_stop1=$(date +%s.%N)
wait "$watch_pid" || { echo "error: the subscriber container failed:" >&2; tail -5 "$run/watch.err" >&2; exit 1; }

fail() { echo "docker-check FAILED: $*" >&2; exit 1; }
state=$(docker inspect -f '{{.State.ExitCode}} {{.RestartCount}} {{.HostConfig.RestartPolicy.Name}}' "$daemon_id")
read -r exit_code restarts policy <<< "$state"
[ "$exit_code" = 0 ] || fail "the daemon exited $exit_code after SIGTERM (logs: $run/compose.log)"
[ "$restarts" = 0 ] || fail "the daemon was restarted $restarts time(s)"
[ "$policy" = on-failure ] || fail "the daemon's restart policy is $policy, not on-failure"
watched=$(grep -c '^frame ' "$run/watch.log" || true)
[ "$watched" -gt 0 ] || fail "the outside subscriber saw no keypoints ($run/watch.err)"
summary=$(docker run --rm -v "$TRACKDEFORM_DATA:/data:ro" --entrypoint python "$TRACKDEFORM_IMAGE" -c '
import glob, json, sys
from orchestrator.cli import main
from contextlib import redirect_stdout
import io
files = sorted(glob.glob("/data/session/episode_*.mcap"))
kp = frames = 0
for f in files:
    buf = io.StringIO()
    with redirect_stdout(buf):
        main(["inspect", "--json", f])
    ch = json.loads(buf.getvalue())["channels"]
    kp += ch.get("/keypoints", 0); frames += ch.get("/cam/cam0/color", 0)
print(len(files), frames, kp)')
read -r episodes frames keypoints <<< "$summary"
[ "$episodes" -gt 0 ] || fail "no finished episode in $run/data/session"
[ "$keypoints" -gt 0 ] || fail "$episodes episodes but no /keypoints recorded"
T_END=$(date +%s)
printf 'docker-check passed: %s episodes, %s frames, %s keypoint messages recorded, %s seen by a subscriber\n' \
    "$episodes" "$frames" "$keypoints" "$watched"
printf 'docker-check times: build %d s, up %d s, daemon stop (SIGTERM to exit) %.1f s, total %d s\n' \
    $((T_BUILD - T0)) $((T_UP - T_BUILD)) "$(awk "BEGIN {print $t_stop1 - $t_stop0}")" $((T_END - T0))
ok=1
