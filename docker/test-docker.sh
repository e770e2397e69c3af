#!/usr/bin/env bash
# `make test-docker` (and `make docker-image`): the container image, built and tested for real.
#
#   docker/test-docker.sh [all|build]       all (default): build, then docker/test_stack.py
#
# 1. A Docker daemon: starts dockerd when none answers (as root; installs Debian's docker.io
#    when it is missing), and stops it again at the end if it started it.
# 2. A compose command: `docker compose` (v2 plugin) when there is one, else `docker-compose`
#    (installs Debian's docker-compose, v1, when neither is there).
# 3. The base image: $RANGEFUSE_BASE if set; python:3.11-slim when it is here or Docker Hub
#    answers within seconds; otherwise rangefuse-base:bookworm, built from Debian packages by
#    docker/base/build.sh when it is not here yet (Docker Hub cannot be reached from our CI).
# 4. The image $RANGEFUSE_IMAGE (rangefuse:latest) from docker/Dockerfile: the virtualenv from
#    PyPI, the numba cache warmed by `rangefuse warmup`. When this machine's pip trusts a CA
#    bundle of its own (a TLS-intercepting proxy), it is copied to docker/certs/ for the build.
# 5. docker/test_stack.py: the compose stack end to end, with one worker killed mid-job.
#
# Environment: RANGEFUSE_IMAGE, RANGEFUSE_BASE, PY (the Python with httpx: .venv/bin/python),
# COMPOSE (a compose command to use), TEST_STACK_ARGS (more arguments for test_stack.py).
set -euo pipefail
cd "$(dirname "$0")/.."

MODE=${1:-all}
IMAGE=${RANGEFUSE_IMAGE:-rangefuse:latest}
LOCAL_BASE=rangefuse-base:bookworm
HUB_BASE=python:3.11-slim
PY=${PY:-.venv/bin/python}
LOG_DIR=build/docker
mkdir -p "$LOG_DIR"
T0=$SECONDS
TIMES=()

say() { printf '[%5d s] test-docker: %s\n' "$((SECONDS - T0))" "$*"; }
timed() {  # timed NAME COMMAND...: runs it, records how long it took, returns its status
    local name=$1 t=$SECONDS rc=0
    shift
    "$@" || rc=$?
    TIMES+=("$(printf "%-34s %5d s" "$name" "$((SECONDS - t))")")
    [ "$rc" = 0 ] || TIMES[-1]+=" (failed: exit status $rc)"
    return "$rc"
}
as_root() {
    if [ "$(id -u)" != 0 ]; then
        say "needs root for: $*"
        return 1
    fi
}
apt_install() {
    as_root "apt-get install $*" || exit 1
    apt-get install -y -q "$@" >/dev/null 2>&1 \
        || { apt-get update -q >/dev/null && apt-get install -y -q "$@" >/dev/null; } \
        || { say "apt-get install $* failed"; exit 1; }
}

# --- 1. the daemon ------------------------------------------------------------------------------
STARTED_DOCKERD=
stop_dockerd() {
    if [ -n "$STARTED_DOCKERD" ] && kill -0 "$STARTED_DOCKERD" 2>/dev/null; then
        say "stopping the dockerd it started (pid $STARTED_DOCKERD)"
        kill -TERM "$STARTED_DOCKERD"
        for _ in $(seq 60); do kill -0 "$STARTED_DOCKERD" 2>/dev/null || break; sleep 0.5; done
    fi
}
trap stop_dockerd EXIT

start_docker() {
    if ! command -v docker >/dev/null 2>&1 || ! command -v dockerd >/dev/null 2>&1; then
        if ! docker info >/dev/null 2>&1; then
            say "installing Debian's docker.io"
            apt_install docker.io
        fi
    fi
    if docker info >/dev/null 2>&1; then
        say "Docker daemon: running already ($(docker info -f '{{.ServerVersion}}'))"
        return
    fi
    as_root "dockerd" || exit 1
    say "starting dockerd (log: $LOG_DIR/dockerd.log)"
    # Detached from this shell's output, so that nothing waits on its pipes.
    setsid dockerd </dev/null >"$LOG_DIR/dockerd.log" 2>&1 &
    STARTED_DOCKERD=$!
    for _ in $(seq 120); do
        docker info >/dev/null 2>&1 && break
        kill -0 "$STARTED_DOCKERD" 2>/dev/null || { tail -20 "$LOG_DIR/dockerd.log"; exit 1; }
        sleep 0.5
    done
    docker info >/dev/null 2>&1 || { say "dockerd did not answer in 60 s"; exit 1; }
    say "Docker daemon: started ($(docker info -f '{{.ServerVersion}}'))"
}

# --- 2. compose ---------------------------------------------------------------------------------
find_compose() {
    if [ -n "${COMPOSE:-}" ]; then
        :
    elif docker compose version >/dev/null 2>&1; then
        COMPOSE="docker compose"
    elif command -v docker-compose >/dev/null 2>&1; then
        COMPOSE=docker-compose
    else
        say "no compose: installing Debian's docker-compose"
        apt_install docker-compose
        COMPOSE=docker-compose
    fi
    say "compose: $COMPOSE ($($COMPOSE version --short 2>/dev/null || $COMPOSE version | head -1))"
}

# --- 3. the base image --------------------------------------------------------------------------
hub_reachable() {  # an answer of any kind within 5 s (401 is the usual one)
    if command -v curl >/dev/null 2>&1; then
        curl -s -o /dev/null --max-time 5 https://registry-1.docker.io/v2/
    else
        timeout 5 bash -c '</dev/tcp/registry-1.docker.io/443' 2>/dev/null
    fi
}
choose_base() {
    if [ -n "${RANGEFUSE_BASE:-}" ]; then
        BASE=$RANGEFUSE_BASE
    elif docker image inspect "$HUB_BASE" >/dev/null 2>&1; then
        BASE=$HUB_BASE
    elif hub_reachable && timeout 600 docker pull -q "$HUB_BASE" >/dev/null; then
        BASE=$HUB_BASE
    else
        say "Docker Hub cannot be reached: the base is $LOCAL_BASE (Debian packages)"
        BASE=$LOCAL_BASE
    fi
    if [ "$BASE" = "$LOCAL_BASE" ] && ! docker image inspect "$BASE" >/dev/null 2>&1; then
        timed "base image (debootstrap)" docker/base/build.sh "$BASE"
    fi
    say "base image: $BASE"
}

# --- 4. the image -------------------------------------------------------------------------------
pip_ca_bundle() {  # the CA bundle this machine's pip is told to trust, if any
    local cert=${PIP_CERT:-}
    if [ -z "$cert" ] && [ -x "$PY" ]; then
        cert=$("$PY" -m pip config get global.cert 2>/dev/null || true)
    fi
    if [ -z "$cert" ] && command -v pip3 >/dev/null 2>&1; then
        cert=$(pip3 config get global.cert 2>/dev/null || true)
    fi
    [ -n "$cert" ] && [ -f "$cert" ] && echo "$cert"
    return 0
}
build_image() {
    local cert
    cert=$(pip_ca_bundle)
    rm -f docker/certs/host-ca.crt
    if [ -n "$cert" ]; then
        say "pip trusts $cert here: the build trusts it too (docker/certs/host-ca.crt)"
        cp "$cert" docker/certs/host-ca.crt
    fi
    local build=(docker build)
    if docker buildx version >/dev/null 2>&1; then
        build+=(--progress=plain)
    else
        build=(env DOCKER_BUILDKIT=0 docker build)  # the classic builder: no buildx here
    fi
    say "building $IMAGE on $BASE (log: $LOG_DIR/build.log)"
    if ! "${build[@]}" --force-rm -f docker/Dockerfile --build-arg "BASE=$BASE" -t "$IMAGE" . \
        >"$LOG_DIR/build.log" 2>&1; then
        tail -40 "$LOG_DIR/build.log"
        say "the image build failed"
        return 1
    fi
    grep -h 'compiled the kernels' "$LOG_DIR/build.log" | sed 's/^/    warmup: /' || true
    # Images of earlier builds of this Dockerfile that no tag names any more.
    docker image prune -f --filter label=org.opencontainers.image.title=rangefuse >/dev/null
    say "image $IMAGE: $(docker image inspect -f '{{.Size}}' "$IMAGE" \
        | awk '{printf "%.0f MB", $1 / 1e6}')"
}

timed "Docker daemon" start_docker
find_compose
choose_base
timed "image build (pip install, warmup)" build_image
STATUS=0
if [ "$MODE" = all ]; then
    # shellcheck disable=SC2086
    timed "stack test (docker/test_stack.py)" \
        "$PY" docker/test_stack.py --image "$IMAGE" --compose "$COMPOSE" ${TEST_STACK_ARGS:-} \
        || STATUS=$?
fi
echo "test-docker: times"
printf '  %s\n' "${TIMES[@]}"
printf '  %-34s %5d s\n' "total" "$((SECONDS - T0))"
exit "$STATUS"
