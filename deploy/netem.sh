#!/bin/sh
# Shapes this container's links with tc netem, then runs the service in its place.
#
#   netem.sh [--shape SUBNET DELAY RATE]... -- COMMAND [ARG]...
#
# Each --shape finds the interface this container has on SUBNET (one compose
# network, one interface) and puts `netem delay DELAY rate RATE` on its egress,
# so every packet this container sends on that network waits DELAY and leaves
# at RATE. Shaping both ends of a network gives each direction the delay, as
# `baton link --latency` does. RATE is a tc rate (25mbit = 25*10^6 bit/s, as
# baton's 25Mbit) or `unlimited`. Needs `cap_add: [NET_ADMIN]` and the host's
# sch_netem module. The testbed configuration (controller_link, drone_link)
# holds the same values; tests/deploy/test_compose.py checks that they agree.
set -eu

usage() {
    echo "usage: netem.sh [--shape SUBNET DELAY RATE]... -- COMMAND [ARG]..." >&2
    exit 2
}

# The interface whose connected route is exactly SUBNET.
interface_on() {
    ip -o -4 route show to exact "$1" |
        awk '{ for (i = 1; i < NF; i++) if ($i == "dev") { print $(i + 1); exit } }'
}

while [ $# -gt 0 ]; do
    case "$1" in
    --shape)
        [ $# -ge 4 ] || usage
        subnet=$2 delay=$3 rate=$4
        shift 4
        dev=$(interface_on "$subnet")
        if [ -z "$dev" ]; then
            echo "netem.sh: this container has no interface on $subnet;" \
                "attach it to the compose network with that subnet" >&2
            exit 1
        fi
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
