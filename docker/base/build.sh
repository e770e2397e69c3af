#!/usr/bin/env bash
# Builds the local base image rangefuse-base:bookworm from Debian packages, for machines that
# cannot reach Docker Hub (and so cannot pull python:3.11-slim): debootstrap writes a minimal
# Debian bookworm with Python 3.11, venv, OpenMP for numba (libgomp1) and CA certificates into
# a temporary folder, and `docker import` turns that folder into an image.
#
#   docker/base/build.sh [IMAGE]        (default rangefuse-base:bookworm; needs root)
#
# Then: docker build -f docker/Dockerfile --build-arg BASE=rangefuse-base:bookworm -t rangefuse .
# Environment: DEBIAN_MIRROR (default http://deb.debian.org/debian), SUITE (bookworm).
set -euo pipefail

IMAGE=${1:-rangefuse-base:bookworm}
SUITE=${SUITE:-bookworm}
MIRROR=${DEBIAN_MIRROR:-http://deb.debian.org/debian}
PACKAGES=python3,python3-venv,libgomp1,ca-certificates

if [ "$(id -u)" != 0 ]; then
    echo "docker/base/build.sh: debootstrap needs root" >&2
    exit 1
fi
if ! command -v debootstrap >/dev/null 2>&1; then
    apt-get install -y -q debootstrap >/dev/null \
        || { apt-get update -q >/dev/null && apt-get install -y -q debootstrap >/dev/null; }
fi

ROOTFS=$(mktemp -d /tmp/rangefuse-base.XXXXXX)
cleanup() {
    # debootstrap mounts /proc and /sys inside the target; never delete through a mount.
    local m
    for m in $(awk -v r="$ROOTFS" 'index($2, r) == 1 {print $2}' /proc/mounts | sort -r); do
        umount -l "$m" || true
    done
    rm -rf --one-file-system "$ROOTFS"
}
trap cleanup EXIT

t0=$SECONDS
echo "docker/base/build.sh: debootstrap $SUITE ($PACKAGES) from $MIRROR"
debootstrap --variant=minbase --include="$PACKAGES" "$SUITE" "$ROOTFS" "$MIRROR" \
    >"$ROOTFS.log" 2>&1 || { tail -30 "$ROOTFS.log" >&2; rm -f "$ROOTFS.log"; exit 1; }
rm -f "$ROOTFS.log"

# Sources for apt inside the image (the Dockerfile installs nothing more from Debian when the
# base already has libgomp1, but a derived image may), and no package caches or docs.
cat >"$ROOTFS/etc/apt/sources.list" <<SOURCES
deb $MIRROR $SUITE main
deb $MIRROR $SUITE-updates main
SOURCES
chroot "$ROOTFS" apt-get clean
rm -rf "$ROOTFS"/var/lib/apt/lists/* "$ROOTFS"/var/cache/apt/*.bin \
    "$ROOTFS"/usr/share/doc/* "$ROOTFS"/usr/share/man/* "$ROOTFS"/usr/share/info/* \
    "$ROOTFS"/var/log/*.log "$ROOTFS"/tmp/*

# `python` as well as `python3`, as in the python:3.11-slim image.
ln -sf python3 "$ROOTFS/usr/bin/python"

tar --numeric-owner -C "$ROOTFS" -c . | docker import \
    --change 'ENV LANG=C.UTF-8 PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["python3"]' \
    --message "debootstrap $SUITE minbase + $PACKAGES" - "$IMAGE" >/dev/null
echo "docker/base/build.sh: $IMAGE built in $((SECONDS - t0)) s" \
    "($(docker image inspect -f '{{.Size}}' "$IMAGE" | awk '{printf "%.0f MB", $1 / 1e6}'))"
