#!/usr/bin/env bash
# Build the images: the base (debootstrap, once, cached) and trackdeform3d on it.
#   docker/build.sh            (make docker-build; root or a docker group member)
# Environment: TRACKDEFORM_IMAGE (default trackdeform3d:latest), BASE_IMAGE (default trackdeform-base:bookworm,
# any Debian bookworm with python3 + venv), EXTRAS (pip extras, e.g. franka,realsense),
# TRACKDEFORM_EXTRA_CA (colon-separated PEM files the build trusts; default the host's CA bundle).
# Exit 3 with "skipped: <reason>" where docker cannot run at all.
set -euo pipefail
cd "$(dirname "$0")/.."
. docker/docker-env.sh
IMAGE="${TRACKDEFORM_IMAGE:-trackdeform3d:latest}"
BASE_IMAGE="${BASE_IMAGE:-trackdeform-base:bookworm}"

rc=0; ensure_docker || rc=$?
if [ "$rc" = 3 ]; then echo "skipped: $SKIP_REASON"; exit 3; elif [ "$rc" != 0 ]; then exit 1; fi

t0=$(date +%s)
docker/base-image.sh "$BASE_IMAGE"
t1=$(date +%s)

# The extra CAs go into docker/ca/ for this build only (gitignored, removed on exit).
ca_files="${TRACKDEFORM_EXTRA_CA-}"
if [ -z "$ca_files" ] && [ -f /etc/ssl/certs/ca-certificates.crt ]; then ca_files=/etc/ssl/certs/ca-certificates.crt; fi
cleanup_ca() { find docker/ca -maxdepth 1 -name 'extra-*.crt' -delete; }
trap 'cleanup_ca; stop_started_dockerd' EXIT
cleanup_ca
n=0
IFS=: read -r -a cas <<< "$ca_files"
for f in "${cas[@]}"; do
    [ -n "$f" ] || continue
    [ -f "$f" ] || { echo "error: TRACKDEFORM_EXTRA_CA: no such file $f" >&2; exit 1; }
    cp "$f" "docker/ca/extra-$n.crt"; n=$((n + 1))
done
echo "building $IMAGE on $BASE_IMAGE (extras '${EXTRAS:-}', $n extra CA file(s))"
docker build -q -f docker/Dockerfile --build-arg BASE="$BASE_IMAGE" --build-arg EXTRAS="${EXTRAS:-}" -t "$IMAGE" . >/dev/null
t2=$(date +%s)
echo "built $IMAGE: base $((t1 - t0)) s, image $((t2 - t1)) s, $(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.2f GB", $1/1e9}')"
