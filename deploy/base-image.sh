#!/bin/sh
# Builds a Debian bookworm base image with Python 3.11 where no image can be
# pulled, and imports it into the local Docker engine:
#
#   deploy/base-image.sh NAME
#
# debootstrap (minbase, plus python3, python3-venv and iproute2) into a
# temporary folder, then `tar | docker import`. The Debian mirror is the one
# this machine's apt already uses for bookworm main (read from `apt-cache
# policy` at run time, never written into the project); DEBIAN_MIRROR=URL
# overrides it. Does nothing if NAME exists already. Needs root, debootstrap
# and a running Docker engine.
set -eu

name=${1:?usage: deploy/base-image.sh NAME}
suite=bookworm

if docker image inspect "$name" >/dev/null 2>&1; then
    echo "base-image.sh: $name exists already" >&2
    exit 0
fi
if ! command -v debootstrap >/dev/null; then
    echo "base-image.sh: debootstrap is missing: apt-get install debootstrap" >&2
    exit 1
fi

mirror=${DEBIAN_MIRROR:-$(apt-cache policy 2>/dev/null |
    awk -v want="$suite/main" '$3 == want && $2 ~ /^https?:\/\// { print $2; exit }')}
if [ -z "$mirror" ]; then
    echo "base-image.sh: apt knows no mirror for '$suite main' (apt-cache policy);" \
        "run 'apt-get update', or set DEBIAN_MIRROR=URL of a Debian mirror" >&2
    exit 1
fi

root=$(mktemp -d "${TMPDIR:-/var/tmp}/baton-base.XXXXXX")
# Removed however the script ends. debootstrap mounts /proc and /sys in the root it
# builds; one stopped midway can leave them mounted: unmounted first, and rm stays
# on the folder's own file system.
remove_root() {
    awk -v under="$root/" 'index($2, under) == 1 { print $2 }' /proc/mounts | sort -r |
        while read -r mount; do umount -l "$mount" 2>/dev/null || true; done
    rm -rf --one-file-system "$root"
}
trap remove_root EXIT
trap 'exit 130' INT TERM
echo "base-image.sh: debootstrap $suite from $mirror into $root" >&2
started=$(date +%s)
debootstrap --variant=minbase --include=python3,python3-venv,iproute2 \
    "$suite" "$root/rootfs" "$mirror" >"$root/debootstrap.log" 2>&1 || {
    tail -n 20 "$root/debootstrap.log" >&2
    echo "base-image.sh: debootstrap failed (its log's end above)" >&2
    exit 1
}
# No package lists or downloaded .debs in the image.
rm -rf "$root"/rootfs/var/cache/apt/archives/*.deb "$root"/rootfs/var/lib/apt/lists/*
tar -C "$root/rootfs" -c . | docker import \
    --change 'ENV PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin' \
    --change 'CMD ["/bin/bash"]' \
    - "$name" >/dev/null
echo "base-image.sh: $name imported ($(($(date +%s) - started)) s)" >&2
