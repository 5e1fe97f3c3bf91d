#!/usr/bin/env bash
# Build the two container images with podman and test them for real (slow: minutes).
#
#   1. installs podman, runc and debootstrap if missing (Debian/Ubuntu, as root),
#   2. imports a Debian bookworm base image with Python 3.11 (no registry needed),
#   3. builds docker/server.Dockerfile and docker/learner.Dockerfile (the learner's torch comes
#      from the CPU wheel in $WHEELS),
#   4. checks the server image refuses its default non-loopback bind without keys,
#   5. generates CURVE keys with the server image (`sim-server keygen`), starts a server
#      container with authentication on, waits for its `listening on` line, then drives
#      $EPISODES IDM episodes through it from a learner container, runs `agent-client check`,
#      and checks that a learner without the keys is not served,
#   6. does by hand what docker/compose.yaml does with `--scale server=2`: an internal network,
#      two servers under one DNS name, and a learner that trains 2 episodes through
#      docker/resolve-servers.sh,
#   7. removes its containers, network and keys volume on exit.
#
# Why the podman flags (docs/docker.md, "Testing the images"): there is no Docker daemon or
# container registry here, hence podman and a debootstrapped base image; podman's default
# runtime crun fails on this VM ("setrlimit RLIMIT_NOFILE: Operation not permitted"), hence
# --runtime /usr/sbin/runc and explicit --ulimit values; pip inside a build reaches the package
# index over the host network and must trust this machine's CA bundle, mounted read-only.
#
# Environment: BASE (base image; default localhost/debian-py:bookworm, built by debootstrap when
# missing), WHEELS (folder with the torch CPU wheel, default /opt/wheels), EPISODES (default 3),
# CHECK=0 to skip the conformance check, SCALE=0 to skip the two-replica train, NO_CACHE=1 to
# build without podman's layer cache (build times from scratch), READY_TIMEOUT (s, default 120).
set -euo pipefail
cd "$(dirname "$0")/.."

BASE=${BASE:-localhost/debian-py:bookworm}
WHEELS=${WHEELS:-/opt/wheels}
EPISODES=${EPISODES:-3}
READY_TIMEOUT=${READY_TIMEOUT:-120}
SERVER_IMAGE=localhost/av-bridge-server
LEARNER_IMAGE=localhost/av-bridge-learner
CA_BUNDLE=/etc/ssl/certs/ca-certificates.crt

podman_() { podman --runtime /usr/sbin/runc "$@"; }
limits=(--ulimit nofile=1024:1024 --ulimit nproc=1024:1024)
say() { printf '== %s\n' "$*"; }
seconds_since() { echo $(($(date +%s) - $1)); }

# ---- 1. tools --------------------------------------------------------------------------------
missing=()
for tool in podman:podman /usr/sbin/runc:runc debootstrap:debootstrap; do
    command -v "${tool%%:*}" >/dev/null || missing+=("${tool##*:}")
done
if [ "${#missing[@]}" -gt 0 ]; then
    say "installing ${missing[*]}"
    apt-get update -qq
    DEBIAN_FRONTEND=noninteractive apt-get install -y -qq "${missing[@]}" >/dev/null
fi
say "$(podman --version), runc $(/usr/sbin/runc --version | head -n 1 | awk '{print $3}')"

# ---- 2. base image ---------------------------------------------------------------------------
if ! podman_ image exists "$BASE"; then
    [ "$BASE" = localhost/debian-py:bookworm ] || { echo "base image $BASE not found"; exit 1; }
    say "building the base image $BASE with debootstrap (1-2 min)"
    rootfs=$(mktemp -d /tmp/debian-py.XXXXXX)
    start=$(date +%s)
    debootstrap --variant=minbase --include=python3,python3-venv,python3-pip,ca-certificates \
        bookworm "$rootfs" >/tmp/debootstrap.log 2>&1 ||
        { tail -n 20 /tmp/debootstrap.log; exit 1; }
    tar -C "$rootfs" -c . | podman_ import - "$BASE" >/dev/null
    rm -rf "$rootfs"
    say "base image built in $(seconds_since "$start") s"
fi

# ---- 3. images -------------------------------------------------------------------------------
build() {  # build NAME DOCKERFILE TAG [podman build args...]
    local name=$1 dockerfile=$2 tag=$3 start
    shift 3
    [ "${NO_CACHE:-0}" = 0 ] || set -- --no-cache "$@"
    start=$(date +%s)
    say "building the $name image ($dockerfile)"
    podman_ build "${limits[@]}" --network host -v "$CA_BUNDLE:$CA_BUNDLE:ro" \
        --build-arg BASE="$BASE" -f "$dockerfile" -t "$tag" "$@" . >"/tmp/build-$name.log" 2>&1 ||
        { tail -n 40 "/tmp/build-$name.log"; echo "build failed, log: /tmp/build-$name.log"; exit 1; }
    eval "build_seconds_$name=$(seconds_since "$start")"
}
build server docker/server.Dockerfile "$SERVER_IMAGE" \
    --build-arg PIP_EXTRA_ARGS="--cert $CA_BUNDLE"
build learner docker/learner.Dockerfile "$LEARNER_IMAGE" -v "$WHEELS:/wheels:ro" \
    --build-arg PIP_EXTRA_ARGS="--cert $CA_BUNDLE --find-links /wheels"
size() { podman_ image inspect --format '{{.Size}}' "$1" | awk '{printf "%.0f MB", $1 / 1e6}'; }
base_size=$(size "$BASE")
server_size=$(size "$SERVER_IMAGE")
learner_size=$(size "$LEARNER_IMAGE")
say "server image:  $server_size, built in ${build_seconds_server} s (log /tmp/build-server.log)"
say "learner image: $learner_size, built in ${build_seconds_learner} s (log /tmp/build-learner.log)"
say "(base image $BASE: $base_size, included in both)"
versions='import importlib.metadata as m, importlib.util as u
print(", ".join(f"{p} {m.version(p)}" if u.find_spec(p) else f"no {p}" for p in ("libsumo", "torch")))'
say "in the server image:  $(podman_ run --rm "${limits[@]}" --entrypoint python "$SERVER_IMAGE" -c "$versions")"
say "in the learner image: $(podman_ run --rm "${limits[@]}" --entrypoint python "$LEARNER_IMAGE" -c "$versions")"

# ---- 4-7. real servers and learners ---------------------------------------------------------
run_id=$$
servers=()  # containers started here
keys=""     # a named volume, as in docker/compose.yaml
network=""
cleanup() {
    local name
    for name in "${servers[@]}"; do
        podman_ rm -f -t 5 "$name" >/dev/null 2>&1 || true
    done
    [ -z "$network" ] || podman_ network rm -f "$network" >/dev/null 2>&1 || true
    [ -z "$keys" ] || podman_ volume rm -f "$keys" >/dev/null 2>&1 || true
}
trap cleanup EXIT

say "the server image's default command (tcp://0.0.0.0:5555) without keys must be refused"
set +e
refusal=$(timeout 60 podman --runtime /usr/sbin/runc run --rm "${limits[@]}" --network none \
    "$SERVER_IMAGE" 2>&1)
status=$?
set -e
if [ "$status" -eq 0 ]; then
    echo "FAIL: sim-server started on 0.0.0.0 without authentication"; exit 1
fi
echo "   refused (exit $status): $(echo "$refusal" | tail -n 1)"

server_auth=()   # sim-server flags
learner_auth=()  # agent-client flags
learner_env=()   # the same through the environment, as docker/compose.yaml does
if podman_ run --rm "${limits[@]}" "$SERVER_IMAGE" --help | grep -q -- '--secret-key'; then
    auth="on"
    keys=av-bridge-test-keys-$run_id
    podman_ volume create "$keys" >/dev/null
    say "generating CURVE keys with the server image into volume $keys: sim-server keygen --out /keys"
    podman_ run --rm "${limits[@]}" --network none -v "$keys:/keys" "$SERVER_IMAGE" \
        keygen --out /keys >/dev/null
    podman_ run --rm "${limits[@]}" --network none -v "$keys:/keys:ro" --entrypoint ls \
        "$SERVER_IMAGE" -ln /keys | tail -n +2 | awk '{print "   " $1, "uid " $3, $NF}'
    server_auth=(--secret-key /keys/server.key_secret --authorized-keys /keys)
    learner_auth=(--server-key /keys/server.key --secret-key /keys/client.key_secret)
    learner_env=(-e AV_BRIDGE_SERVER_KEY=/keys/server.key -e AV_BRIDGE_SECRET_KEY=/keys/client.key_secret)
    mounts=(-v "$keys:/keys:ro")
else
    auth="off"
    say "this sim-server has no --secret-key yet: testing WITHOUT authentication"
    mounts=()
fi

start_server() {  # start_server NAME ADDRESS PODMAN-ARGS...: run a server, wait for `listening on`
    local name=$1 address=$2 start listening="" bind_args=()
    shift 2
    [ "$auth" = on ] || [[ "$address" == tcp://127.* ]] || bind_args=(--insecure)
    say "starting server container $name on $address (authentication $auth)"
    servers+=("$name")
    # (stderr kept aside: netavark prints "failed to connect to syslog" on this VM)
    podman_ run -d --name "$name" "${limits[@]}" "$@" "${mounts[@]}" \
        "$SERVER_IMAGE" --bind "$address" "${server_auth[@]}" "${bind_args[@]}" \
        >/dev/null 2>/tmp/podman-run.err || { cat /tmp/podman-run.err; exit 1; }
    start=$(date +%s)
    while :; do
        listening=$(podman_ logs "$name" 2>/dev/null | sed -n 's/^listening on //p' | head -n 1)
        [ -n "$listening" ] && break
        if [ "$(podman_ container inspect -f '{{.State.Running}}' "$name")" != true ]; then
            echo "FAIL: $name exited:"; podman_ logs "$name" 2>&1 | tail -n 20; exit 1
        fi
        if [ "$(seconds_since "$start")" -ge "$READY_TIMEOUT" ]; then
            echo "FAIL: $name printed no 'listening on' line within $READY_TIMEOUT s"
            podman_ logs "$name" 2>&1 | tail -n 20; exit 1
        fi
        sleep 0.2
    done
    say "$name ready in $(seconds_since "$start") s: listening on $listening"
}
hellos() { podman_ logs "$1" 2>&1 | grep -c 'hello from' || true; }

# -- one server on the host network (no port mapping needed); loopback, so nothing is exposed
port=$(python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')
address=tcp://127.0.0.1:$port
first=av-bridge-test-server-$run_id
start_server "$first" "$address" --network host

learner() {  # learner SUBCOMMAND ARGS...: agent-client in a container, with the keys if any
    local subcommand=$1
    shift
    podman_ run --rm "${limits[@]}" --network host "${mounts[@]}" "$LEARNER_IMAGE" \
        "$subcommand" --server "$address" "${learner_auth[@]}" "$@"
}

cache_before=$(podman_ exec "$first" sh -c 'ls ~/.cache/av-bridge/scenarios' | tr '\n' ' ')
say "learner container: agent-client drive --policy idm --episodes $EPISODES"
start=$(date +%s)
learner drive --scenario cf --policy idm --episodes "$EPISODES" --timeout 60
say "drive took $(seconds_since "$start") s (container start included)"
cache_after=$(podman_ exec "$first" sh -c 'ls ~/.cache/av-bridge/scenarios' | tr '\n' ' ')
if [ "$cache_before" = "$cache_after" ]; then
    say "scenario cache: $cache_after- prebuilt at image build time, reused (no netconvert)"
else
    say "scenario cache: $cache_before-> $cache_after- the first reset had to build (not prebuilt)"
fi

if [ "${CHECK:-1}" != 0 ]; then
    say "learner container: agent-client check (protocol conformance)"
    start=$(date +%s)
    learner check --scenario cf
    say "check took $(seconds_since "$start") s"
fi

if [ "$auth" = on ]; then
    say "a learner without the keys must not be served"
    set +e
    podman_ run --rm "${limits[@]}" --network host "$LEARNER_IMAGE" \
        drive --server "$address" --policy idm --episodes 1 --timeout 5 >/tmp/unauth.log 2>&1
    status=$?
    set -e
    if [ "$status" -eq 0 ]; then
        echo "FAIL: an unauthenticated learner drove an episode"; exit 1
    fi
    echo "   refused (exit $status): $(tail -n 1 /tmp/unauth.log)"
fi

# -- what docker/compose.yaml does with `--scale server=2`, by hand (no Docker Compose here):
# an internal network, two servers under one DNS name binding tcp://0.0.0.0:5555 with the keys
# volume, and a learner that starts through resolve-servers with the keys in its environment.
if [ "${SCALE:-1}" != 0 ]; then
    network=av-bridge-test-net-$run_id
    podman_ network create --internal "$network" >/dev/null
    say "internal network $network, 2 servers with the network alias 'server'"
    replicas=()
    for i in 1 2; do
        replicas+=("av-bridge-test-replica-$run_id-$i")
        start_server "${replicas[-1]}" tcp://0.0.0.0:5555 --network "$network" --network-alias server
    done
    # docker/compose.yaml's healthcheck command
    podman_ exec "${replicas[0]}" python -c \
        "import socket; socket.create_connection(('127.0.0.1', 5555), 2).close()"
    say "compose healthcheck command: exit 0"
    say "learner container: resolve-servers server:5555 agent-client train --config configs/cf.toml --episodes 2"
    start=$(date +%s)
    podman_ run --rm "${limits[@]}" --network "$network" "${mounts[@]}" "${learner_env[@]}" \
        --entrypoint resolve-servers "$LEARNER_IMAGE" server:5555 agent-client \
        train --config configs/cf.toml --scenario cf --episodes 2 --set eval_every=0 --quiet \
        --out /tmp/scale-test 2>&1 |
        grep -v '^\s*$' | tail -n 8 | sed 's/^/   /'
    served1=$(hellos "${replicas[0]}")
    served2=$(hellos "${replicas[1]}")
    say "train took $(seconds_since "$start") s; clients served: replica 1: $served1, replica 2: $served2"
    if [ "$served1" -gt 0 ] && [ "$served2" -gt 0 ]; then
        scaling="train used both replicas"
    else
        scaling="train used ONE of 2 replicas (agent-client train keeps the last --server)"
    fi
fi

say "server log (last lines):"
podman_ logs "$first" 2>&1 | tail -n 4 | sed 's/^/   /'
say "OK: images $SERVER_IMAGE ($server_size) and $LEARNER_IMAGE ($learner_size), authentication $auth"
[ -z "${scaling:-}" ] || say "scaling: $scaling"
