#!/usr/bin/env bash
# Build the base image once: Debian bookworm (debootstrap minbase) with Python 3.11, venv and pip,
# imported into docker as $BASE_IMAGE. Image registries are not needed. Reused when it exists.
#   docker/base-image.sh [IMAGE]      (default trackdeform-base:bookworm; root, debootstrap, docker)
set -euo pipefail
BASE_IMAGE="${1:-${BASE_IMAGE:-trackdeform-base:bookworm}}"
MIRROR="${DEBIAN_MIRROR:-http://deb.debian.org/debian}"
if docker image inspect "$BASE_IMAGE" >/dev/null 2>&1; then
    echo "base image $BASE_IMAGE exists (docker rmi $BASE_IMAGE to rebuild it)"
    exit 0
fi
command -v debootstrap >/dev/null || { echo "error: debootstrap is not installed (apt-get install debootstrap)" >&2; exit 1; }
root="$(mktemp -d /var/tmp/trackdeform-rootfs.XXXXXX)"
trap 'rm -rf "$root"' EXIT
echo "debootstrap bookworm into $root (mirror $MIRROR)"
debootstrap --variant=minbase \
    --include=python3,python3-venv,python3-pip,ca-certificates \
    bookworm "$root" "$MIRROR" > "$root.log" 2>&1 || { tail -20 "$root.log" >&2; rm -f "$root.log"; exit 1; }
rm -f "$root.log"
# A smaller image: no apt lists or caches (the Dockerfile runs apt-get update itself).
rm -rf "$root"/var/lib/apt/lists/* "$root"/var/cache/apt/*.bin "$root"/var/cache/apt/archives/*.deb
tar -C "$root" --numeric-owner -c . | docker import \
    --change 'ENV LANG=C.UTF-8' --change 'CMD ["/bin/bash"]' - "$BASE_IMAGE" >/dev/null
echo "base image $BASE_IMAGE built: $(docker run --rm "$BASE_IMAGE" python3 --version)"
