#!/bin/sh
# `make image`: builds the compose testbed's images in the local Docker engine.
#
#   baton-testbed:dev         deploy/Dockerfile, baton installed from a wheelhouse
#                             built here (`pip wheel`), so no network in the build
#   baton-ardupilot-sitl:dev  deploy/Dockerfile.sitl, from the ArduCopter SITL build
#                             `baton sitl --which` finds (BATON_SITL_BINARY, else
#                             arducopter on PATH) and its copter.parm (BATON_SITL_PARM,
#                             else the one beside the build or in its ArduPilot tree,
#                             else ../shared/ardupilot/copter.parm), staged in build/sitl
#                             (the compose file's build context `sitl`); where there
#                             is none, the image is left out and this says why
#
# BATON_BASE chooses the base image:
#   auto (default)  the public python:3.11-slim-bookworm if the engine has it or
#                   can pull it, else the local one below
#   public          python:3.11-slim-bookworm (and debian:bookworm-slim for SITL)
#   local           baton-base:bookworm, made by deploy/base-image.sh with
#                   debootstrap where no image can be pulled; the builds then
#                   run with --network none
# PYTHON is the Python 3.11 that runs `pip wheel` (the Makefile's virtualenv).
set -eu
cd "$(dirname "$0")/.."

python=${PYTHON:-python3}
base=${BATON_BASE:-auto}
sitl_dir=build/sitl # the compose file's build context `sitl`
public=python:3.11-slim-bookworm
public_sitl=debian:bookworm-slim
local_base=baton-base:bookworm
wheelhouse=build/wheelhouse # in the build context; deploy/Dockerfile removes it from the image

say() { echo "images.sh: $*" >&2; }
timed() { # timed WHAT COMMAND...: runs COMMAND, says how long it took
    what=$1
    shift
    t0=$(date +%s)
    "$@"
    say "$what: $(($(date +%s) - t0)) s"
}

if ! docker info >/dev/null 2>&1; then
    say "no Docker engine answers 'docker info': start one (make compose-test starts" \
        "dockerd itself), or set DOCKER_HOST"
    exit 1
fi

case $base in
auto)
    if docker image inspect "$public" >/dev/null 2>&1 || docker pull -q "$public" >/dev/null 2>&1; then
        base=public
    else
        say "$public cannot be pulled here: using the local base $local_base"
        base=local
    fi
    ;;
public)
    for image in "$public" "$public_sitl"; do
        if ! docker image inspect "$image" >/dev/null 2>&1 && ! docker pull -q "$image" >/dev/null; then
            say "BATON_BASE=public, but $image cannot be pulled: use BATON_BASE=local" \
                "(a debootstrap base) on a machine without an image registry"
            exit 1
        fi
    done
    ;;
local) ;;
*)
    say "BATON_BASE must be auto, public or local, not '$base' (make image BATON_BASE=local)"
    exit 2
    ;;
esac

if [ "$base" = local ]; then
    timed "base image $local_base" deploy/base-image.sh "$local_base"
    from=$local_base from_sitl=$local_base network=none
else
    from=$public from_sitl=$public_sitl network=default
fi

rm -rf "$wheelhouse"
mkdir -p "$wheelhouse"
timed "wheelhouse $wheelhouse (pip wheel)" \
    "$python" -m pip wheel --quiet --disable-pip-version-check --wheel-dir "$wheelhouse" .

timed "image baton-testbed:dev on $from" \
    docker build --quiet --network "$network" -f deploy/Dockerfile \
    --build-arg BASE="$from" --build-arg WHEELHOUSE="$wheelhouse" \
    -t baton-testbed:dev . >/dev/null

# The SITL build where users keep it, found by the one lookup baton uses.
rm -rf "$sitl_dir"
sitl_binary=
sitl_parm=
if found=$("$python" -m baton.cli sitl --which 2>/tmp/baton-sitl-which.$$); then
    sitl_binary=$(printf '%s\n' "$found" | sed -n 1p)
    sitl_parm=${BATON_SITL_PARM:-$(printf '%s\n' "$found" | sed -n 2p)}
    if [ -z "$sitl_parm" ] && [ -f ../shared/ardupilot/copter.parm ]; then
        sitl_parm=../shared/ardupilot/copter.parm
    fi
fi
sitl_missing=$(cat /tmp/baton-sitl-which.$$)
rm -f /tmp/baton-sitl-which.$$
if [ -n "$sitl_binary" ] && [ -z "$sitl_parm" ]; then
    sitl_missing="no copter.parm for $sitl_binary: set BATON_SITL_PARM"
fi
if [ -n "$sitl_binary" ] && [ -n "$sitl_parm" ]; then
    mkdir -p "$sitl_dir"
    cp "$sitl_binary" "$sitl_dir/arducopter"
    cp "$sitl_parm" "$sitl_dir/copter.parm"
    # The files as an image, for builders without named build contexts.
    tar -C "$sitl_dir" -c arducopter copter.parm |
        docker import --change "LABEL baton.image=sitl-files" - baton-sitl-files:dev >/dev/null
    timed "image baton-ardupilot-sitl:dev on $from_sitl" \
        docker build --quiet --network "$network" -f deploy/Dockerfile.sitl \
        --build-arg BASE="$from_sitl" --build-arg SITL_FILES=baton-sitl-files:dev \
        -t baton-ardupilot-sitl:dev deploy >/dev/null
else
    say "baton-ardupilot-sitl:dev not built: $sitl_missing"
fi
# Each build leaves the previous image and the build stage untagged: remove
# those (only images with the Dockerfiles' label, only dangling ones).
docker image prune -f --filter label=baton.image >/dev/null
docker image ls --format '{{.Repository}}:{{.Tag}} {{.Size}}' | grep '^baton-' >&2 || true
