#!/bin/sh
# resolve-servers NAME:PORT PROGRAM SUBCOMMAND [ARGS...]
#
# Runs `PROGRAM SUBCOMMAND --server tcp://IP:PORT ... ARGS...` with one --server per IPv4
# address of NAME. With `docker compose up --scale server=N`, Docker's DNS answers the service
# name `server` with the addresses of all N replicas, but a ZeroMQ connect to a name uses only
# one of them: this turns them into N explicit addresses, one simulator each.
#
# `train` gets every address (one simulator per address, a vector env); other subcommands
# (drive, evaluate, check...) talk to one server and get the first one. The addresses are read
# once, at start: a replica added or restarted later is not seen. Waits at most
# RESOLVE_TIMEOUT seconds (default 60) for NAME to resolve.
set -eu

if [ "$#" -lt 3 ]; then
    echo "usage: resolve-servers NAME:PORT PROGRAM SUBCOMMAND [ARGS...]" >&2
    exit 64
fi
target=$1
program=$2
subcommand=$3
shift 3
name=${target%:*}
port=${target##*:}
if [ -z "$name" ] || [ "$name" = "$target" ] || [ -z "$port" ]; then
    echo "resolve-servers: expected NAME:PORT, got '$target'" >&2
    exit 64
fi

timeout=${RESOLVE_TIMEOUT:-60}
start=$(date +%s)
while :; do
    addresses=$(getent ahostsv4 "$name" | awk '{print $1}' | sort -u -t. -k1,1n -k2,2n -k3,3n -k4,4n || true)
    [ -n "$addresses" ] && break
    if [ $(($(date +%s) - start)) -ge "$timeout" ]; then
        echo "resolve-servers: '$name' did not resolve within ${timeout} s" >&2
        exit 69
    fi
    sleep 1
done

if [ "$subcommand" != "train" ]; then
    addresses=$(echo "$addresses" | head -n 1)
fi
servers=""
for address in $addresses; do
    servers="$servers --server tcp://$address:$port"
done
echo "resolve-servers: $name ->$servers" >&2
# $servers is split on spaces on purpose: addresses and ports contain none.
# shellcheck disable=SC2086
exec "$program" "$subcommand" $servers "$@"
