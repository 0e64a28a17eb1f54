#!/usr/bin/env bash
# `make compose-test`: the compose testbed for real, on a machine like our CI's
# (root, Debian's packages reachable, no image registry, loopback only).
#
#  1. installs what is missing: docker.io, debootstrap, docker-compose (apt-get)
#  2. starts dockerd if no engine answers (and stops it again at the end)
#  3. builds the images (deploy/images.sh, i.e. `make image`)
#  4. runs deploy/compose.ci.yml: the paper's grid mission, 3 controllers,
#     the handovers of deploy/handovers.txt, on the sim vehicle, or on
#     ArduPilot SITL with BATON_COMPOSE_VEHICLE=ardupilot (needs the SITL
#     image: BATON_SITL_BINARY or arducopter on PATH, see deploy/images.sh)
#  5. waits for the report service's verdict, brings everything down
#  6. the same with radio range (compose.ci.radio.yml over compose.ci.yml):
#     a 1 km corridor, 3 stations of 500 m range, the nearest policy, no
#     handover script, each link to the drone up only while the sim vehicle
#     is within its station's range
#  7. a fleet (compose.ci.fleet.yml): examples/fleet.yaml's 3 stations, each a
#     `baton station`, its 2 drones, each a sim vehicle and a drone service,
#     and the fleet job that admits, starts and judges every mission
#
# BATON_COMPOSE_RUNS chooses the runs (default "grid radio fleet"; the radio and
# fleet runs need the sim vehicle). Exits 0 only if every report is a pass
# (completed, exactly once, replicas consistent; the radio run also masters 0,
# 1, 2 by the policy alone; the fleet run every mission exactly once at its
# vehicle and camera with consistent replicas); reports/report.json,
# reports/report-radio.json and reports/report-fleet.json hold them.
# Every wait has a deadline (in seconds, from the environment):
#   BATON_DOCKERD_DEADLINE (60)   for a started dockerd to answer
#   BATON_BUILD_DEADLINE (1500)   for the images to build
#   BATON_UP_DEADLINE (300)       for `compose up` (the drone healthy, the links listening)
#   BATON_REPORT_DEADLINE (420)   for the report service (the fleet job) to exit
#   BATON_DOWN_DEADLINE (120)     for `compose down`, and for dockerd to stop
# BATON_DOCKERD_STORAGE: storage drivers to try in order (default "overlay2 vfs").
set -euo pipefail
cd "$(dirname "$0")/.."

DOCKERD_DEADLINE=${BATON_DOCKERD_DEADLINE:-60}
BUILD_DEADLINE=${BATON_BUILD_DEADLINE:-1500}
UP_DEADLINE=${BATON_UP_DEADLINE:-300}
REPORT_DEADLINE=${BATON_REPORT_DEADLINE:-420}
DOWN_DEADLINE=${BATON_DOWN_DEADLINE:-120}
STORAGE_DRIVERS=${BATON_DOCKERD_STORAGE:-overlay2 vfs}
VEHICLE=${BATON_COMPOSE_VEHICLE:-sim}
RUNS=${BATON_COMPOSE_RUNS:-grid radio fleet}
PROJECT=baton-ci
BASE_COMPOSE=(docker-compose -p "$PROJECT")
CI_COMPOSE=(-f deploy/compose.ci.yml)
case $VEHICLE in
sim) ;;
ardupilot)
    CI_COMPOSE+=(--profile ardupilot)
    export BATON_VEHICLE_URL=tcpout://127.0.0.1:5760
    ;;
*)
    echo "compose-test: BATON_COMPOSE_VEHICLE must be sim or ardupilot, not '$VEHICLE'" >&2
    exit 2
    ;;
esac
for run in $RUNS; do
    case $run in
    grid | radio | fleet) ;;
    *)
        echo "compose-test: BATON_COMPOSE_RUNS lists grid, radio and/or fleet, not '$run'" >&2
        exit 2
        ;;
    esac
done
if [ "$VEHICLE" = ardupilot ] && [[ " $RUNS " == *" radio "* ]]; then
    echo "compose-test: the radio run needs the sim vehicle's position file: with" \
        "BATON_COMPOSE_VEHICLE=ardupilot set BATON_COMPOSE_RUNS=grid" >&2
    exit 2
fi
if [ "$VEHICLE" = ardupilot ] && [[ " $RUNS " == *" fleet "* ]]; then
    echo "compose-test: the fleet run flies a sim vehicle per drone: with" \
        "BATON_COMPOSE_VEHICLE=ardupilot set BATON_COMPOSE_RUNS=grid" >&2
    exit 2
fi
COMPOSE=("${BASE_COMPOSE[@]}" "${CI_COMPOSE[@]}")

started_at=$(date +%s)
say() { echo "compose-test: [$(($(date +%s) - started_at)) s] $*" >&2; }

# -- 1. what it needs ------------------------------------------------------------
missing=()
command -v dockerd >/dev/null || missing+=(docker.io)
command -v debootstrap >/dev/null || missing+=(debootstrap)
command -v docker-compose >/dev/null || missing+=(docker-compose)
if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" != 0 ]; then
        say "missing ${missing[*]}, and only root installs them: sudo apt-get install ${missing[*]}"
        exit 1
    fi
    say "installing ${missing[*]} (apt-get)"
    timeout "$BUILD_DEADLINE" apt-get update -qq
    DEBIAN_FRONTEND=noninteractive timeout "$BUILD_DEADLINE" \
        apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

# -- 2. a Docker engine ------------------------------------------------------------
dockerd_pid=
dockerd_log=$(mktemp "${TMPDIR:-/tmp}/baton-dockerd.XXXXXX.log")
compose_up=

stop_dockerd() {
    [ -n "$dockerd_pid" ] || return 0
    say "stopping the dockerd this run started (pid $dockerd_pid)"
    kill -TERM "$dockerd_pid" 2>/dev/null || true
    local deadline=$(($(date +%s) + DOWN_DEADLINE))
    while kill -0 "$dockerd_pid" 2>/dev/null; do
        if [ "$(date +%s)" -ge "$deadline" ]; then
            say "dockerd (pid $dockerd_pid) did not stop within ${DOWN_DEADLINE} s of SIGTERM: killing it"
            kill -KILL "$dockerd_pid" 2>/dev/null || true
            break
        fi
        sleep 0.5
    done
    wait "$dockerd_pid" 2>/dev/null || true
    dockerd_pid=
    # dockerd leaves its network namespace mounted; nothing else uses it now.
    umount /run/docker/netns/default 2>/dev/null || true
}

bring_down() {
    [ -n "$compose_up" ] || return 0
    compose_up=
    say "bringing the testbed down"
    timeout "$DOWN_DEADLINE" "${COMPOSE[@]}" down -v --remove-orphans --timeout 10 >/dev/null 2>&1 ||
        say "'compose down' did not finish within ${DOWN_DEADLINE} s (or failed)"
}

cleanup() {
    local rc=$?
    bring_down
    stop_dockerd
    rm -f "$dockerd_log"
    say "done in $(($(date +%s) - started_at)) s, exit $rc"
    exit "$rc"
}
trap cleanup EXIT
trap 'exit 130' INT TERM

if docker info >/dev/null 2>&1; then
    say "using the Docker engine that runs already"
else
    for driver in $STORAGE_DRIVERS; do
        say "starting dockerd (storage driver $driver)"
        dockerd --storage-driver="$driver" --bridge=none --iptables=false >"$dockerd_log" 2>&1 &
        dockerd_pid=$!
        deadline=$(($(date +%s) + DOCKERD_DEADLINE))
        until docker info >/dev/null 2>&1; do
            if ! kill -0 "$dockerd_pid" 2>/dev/null || [ "$(date +%s)" -ge "$deadline" ]; then
                tail -n 5 "$dockerd_log" >&2
                say "dockerd with $driver did not answer 'docker info' within ${DOCKERD_DEADLINE} s (its log's end above)"
                stop_dockerd
                break
            fi
            sleep 0.5
        done
        [ -z "$dockerd_pid" ] || break
    done
    if [ -z "$dockerd_pid" ]; then
        say "no Docker engine could be started (tried: $STORAGE_DRIVERS)"
        exit 1
    fi
fi

# -- 3. the images ----------------------------------------------------------------
say "building the images (deploy/images.sh)"
if ! timeout "$BUILD_DEADLINE" deploy/images.sh; then
    say "the images did not build within ${BUILD_DEADLINE} s (or failed, see above)"
    exit 1
fi

# -- 4. the runs -------------------------------------------------------------------
if [ "$VEHICLE" = ardupilot ] && ! docker image inspect baton-ardupilot-sitl:dev >/dev/null 2>&1; then
    say "BATON_COMPOSE_VEHICLE=ardupilot, but no baton-ardupilot-sitl:dev was built: set" \
        "BATON_SITL_BINARY to an ArduCopter SITL build or put arducopter on PATH" \
        "(https://ardupilot.org/dev/docs/building-setup-linux.html)"
    exit 1
fi
mkdir -p reports

# run_mission NAME REPORT SERVICE COMPOSE-OPTION...: one run from compose up to its
# verdict (SERVICE's exit, the report service or the fleet job, and its file REPORT),
# then compose down.
run_mission() {
    local name=$1 report=$2 service=$3
    shift 3
    COMPOSE=("${BASE_COMPOSE[@]}" "$@")
    rm -f "$report"
    timeout "$DOWN_DEADLINE" "${COMPOSE[@]}" down -v --remove-orphans >/dev/null 2>&1 || true
    compose_up=1
    say "$name: compose up ($VEHICLE): $*"
    if ! timeout "$UP_DEADLINE" "${COMPOSE[@]}" up -d --no-build; then
        "${COMPOSE[@]}" ps >&2 || true
        "${COMPOSE[@]}" logs --no-color --tail 20 >&2 || true
        say "$name: the testbed did not come up within ${UP_DEADLINE} s (what each part waits for: its depends_on)"
        exit 1
    fi
    local report_id verdict waited
    report_id=$("${COMPOSE[@]}" ps -q "$service")
    say "$name: waiting for the $service service's verdict (container ${report_id:0:12}, at most ${REPORT_DEADLINE} s)"
    set +e
    verdict=$(timeout "$REPORT_DEADLINE" docker wait "$report_id")
    waited=$?
    set -e
    "${COMPOSE[@]}" logs --no-color "$service" >&2 || true
    if [ "$waited" -ne 0 ]; then
        "${COMPOSE[@]}" logs --no-color --tail 30 >&2 || true
        say "$name: no verdict: the $service service did not exit within ${REPORT_DEADLINE} s"
        exit 1
    fi
    if [ "$verdict" != 0 ]; then
        "${COMPOSE[@]}" logs --no-color --tail 30 >&2 || true
        say "$name: FAILED: the $service service exited $verdict (not a pass; $report if it got that far)"
        exit 1
    fi
    if [ ! -s "$report" ]; then
        say "$name: FAILED: the $service service exited 0 but wrote no $report"
        exit 1
    fi
    # The verdict once more, from the file: the report's own three promises (the
    # fleet's: each mission's, and every mission there); for the radio run also its
    # story: no script, the policy handing over along the corridor (masters 0, 1,
    # 2), and the links' radio range seen in their logs.
    if ! python3 - "$report" "$name" <<'CHECK'; then
import json, sys
path, name = sys.argv[1], sys.argv[2]
report = json.load(open(path))
if name == "fleet":
    missions = report.get("missions", [])
    failed = [
        f"drone {m.get('drone')}: {k}"
        for m in missions
        for k in ("exactly_once", "replicas_consistent", "ok")
        if m.get(k) is not True
    ]
    if not missions or report.get("summary", {}).get("ok") != len(missions):
        failed.append(f"summary {report.get('summary')} (expected every mission ok)")
else:
    failed = [k for k in ("completed", "exactly_once", "replicas_consistent") if report.get(k) is not True]
if name == "radio":
    if report.get("masters") != [0, 1, 2]:
        failed.append(f"masters {report.get('masters')} (expected [0, 1, 2])")
    triggers = sorted({h.get("trigger") for h in report.get("handovers", [])})
    if triggers != ["policy"]:
        failed.append(f"handover triggers {triggers} (expected policy only)")
sys.exit(f"{path}: not as expected: {', '.join(failed)}" if failed else 0)
CHECK
        say "$name: FAILED: $report is not a pass"
        exit 1
    fi
    if [ "$name" = radio ]; then
        # The links' radio range, from their logs: station 0's link saw the vehicle
        # leave, station 2's saw it arrive, station 1's both (the log read whole
        # first: `grep -q` stopping early would break the pipe under pipefail).
        local check link msg link_log
        for check in "0:vehicle out of radio range" "1:vehicle in radio range" \
            "1:vehicle out of radio range" "2:vehicle in radio range"; do
            link=link-drone-${check%%:*} msg=${check#*:}
            link_log=$("${COMPOSE[@]}" logs --no-color "$link" 2>&1 || true)
            if ! grep -q "\"$msg\"" <<<"$link_log"; then
                say "$name: FAILED: $link never logged \"$msg\""
                exit 1
            fi
        done
    fi
    if [ "$name" = fleet ]; then
        say "$name: PASS: every mission exactly once, replicas consistent ($report)"
    else
        say "$name: PASS: completed, exactly once, replicas consistent ($report)"
    fi
    bring_down
}

for run in $RUNS; do
    case $run in
    grid) run_mission grid reports/report.json report "${CI_COMPOSE[@]}" ;;
    radio) run_mission radio reports/report-radio.json report "${CI_COMPOSE[@]}" -f deploy/compose.ci.radio.yml ;;
    fleet) run_mission fleet reports/report-fleet.json fleet -f deploy/compose.ci.fleet.yml ;;
    esac
done
say "PASS: ${RUNS// /, }"
