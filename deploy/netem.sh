#!/bin/sh
# Shapes this container's links with tc netem, then runs the service in its place.
#
#   netem.sh [--shape SUBNET DELAY RATE | --drop SUBNET]... -- COMMAND [ARG]...
#
# Each --shape finds the interface this container has on SUBNET (one compose
# network, one interface) and puts `netem delay DELAY rate RATE` on its egress,
# so every packet this container sends on that network waits DELAY and leaves
# at RATE. Shaping both ends of a network gives each direction the delay, as
# `baton link --latency` does. RATE is a tc rate (25mbit = 25*10^6 bit/s, as
# baton's 25Mbit) or `unlimited`. Needs `cap_add: [NET_ADMIN]` and the host's
# sch_netem module. The testbed configuration (controller_link, drone_link)
# holds the same values; tests/deploy/test_compose.py checks that they agree.
# --drop puts `netem loss 100%` on SUBNET's interface instead: nothing this
# container sends there arrives. With radio range (deploy/radio.yml) a
# controller starts with its link to the drone dropped, and its `baton
# radio-netem` sidecar opens it while the vehicle is in range.
set -eu

usage() {
    echo "usage: netem.sh [--shape SUBNET DELAY RATE | --drop SUBNET]... -- COMMAND [ARG]..." >&2
    exit 2
}

# The interface whose connected route is exactly SUBNET.
interface_on() {
    ip -o -4 route show to exact "$1" |
        awk '{ for (i = 1; i < NF; i++) if ($i == "dev") { print $(i + 1); exit } }'
}

# The interface on SUBNET, or a clear error and exit.
interface_or_die() {
    dev=$(interface_on "$1")
    if [ -z "$dev" ]; then
        echo "netem.sh: this container has no interface on $1;" \
            "attach it to the compose network with that subnet" >&2
        exit 1
    fi
}

while [ $# -gt 0 ]; do
    case "$1" in
    --drop)
        [ $# -ge 2 ] || usage
        subnet=$2
        shift 2
        interface_or_die "$subnet"
        tc qdisc replace dev "$dev" root netem loss 100%
        echo "netem.sh: $dev ($subnet): loss 100%" >&2
        ;;
    --shape)
        [ $# -ge 4 ] || usage
        subnet=$2 delay=$3 rate=$4
        shift 4
        interface_or_die "$subnet"
        if [ "$rate" = unlimited ]; then
            tc qdisc replace dev "$dev" root netem delay "$delay"
        else
            tc qdisc replace dev "$dev" root netem delay "$delay" rate "$rate"
        fi
        echo "netem.sh: $dev ($subnet): delay $delay rate $rate" >&2
        ;;
    --)
        shift
        break
        ;;
    *)
        usage
        ;;
    esac
done
[ $# -gt 0 ] || usage
exec "$@"
