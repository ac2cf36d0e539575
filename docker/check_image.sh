#!/usr/bin/env bash
# `make images` (docker/check_image.sh [cpu]) builds the CPU image from docker/Dockerfile with buildah and runs it,
# on a machine with no Docker daemon and no image registry (docker/README.md, "Verified on our machines");
# `make images-cuda` (docker/check_image.sh cuda) does the same with docker/Dockerfile.cuda, running on the CPU:
#   1. a Debian bookworm base made with mmdebstrap from Debian's package registry (cached in build/images/);
#   2. `buildah bud --isolation chroot` of docker/Dockerfile on that base, pip using the host's pip configuration;
#   3. in the built root: `bcf --version`, a `--preset fast` compress of examples/sample, and the compose
#      topology: Redis, `bcf serve` and `bcf worker` in two containers sharing one /data, one job POSTed
#      through the API until it succeeds and its artifacts zip is downloaded and checked.
# Exits 0 only when every step passed. Runs itself under sudo when not root.
set -euo pipefail
cd "$(dirname "$0")/.."
# buildah's storage in /var/lib/containers and chroot isolation need root.
[ "$(id -u)" -eq 0 ] || exec sudo "$0" "$@"

variant=${1:-cpu}
case "$variant" in
    # The CPU image takes the CPU torch pinned in constraints.txt (a local file on our machines); the CUDA image
    # takes the newest torch the host's pip allows from its own index, which on Linux is a CUDA build.
    cpu) dockerfile=docker/Dockerfile; torch_spec=$(grep -E '^torch==' constraints.txt) ;;
    cuda) dockerfile=docker/Dockerfile.cuda; torch_spec="torch>=2.3" ;;
    *) echo "usage: $0 [cpu|cuda]" >&2; exit 2 ;;
esac
BASE_IMAGE=localhost/bcf-base:bookworm
IMAGE=localhost/bcf:$variant
WORK=build/images
TOKEN=check-image-token

step() { printf '\n== [%4ss] %s\n' "$SECONDS" "$*"; }
fail() { echo "check_image: FAILED: $*" >&2; exit 1; }

step "tools: buildah, mmdebstrap, redis-server, curl"
need=()
for pkg in buildah mmdebstrap redis-server curl; do
    dpkg -s "$pkg" >/dev/null 2>&1 || need+=("$pkg")
done
if [ ${#need[@]} -gt 0 ]; then
    sudo=""; [ "$(id -u)" -eq 0 ] || sudo="sudo"
    $sudo apt-get update -q
    $sudo apt-get install -y -q "${need[@]}"
fi
mkdir -p "$WORK"

step "base image $BASE_IMAGE"
if buildah inspect --type image "$BASE_IMAGE" >/dev/null 2>&1; then
    echo "already in buildah's storage"
else
    if [ ! -s "$WORK/base.tar" ]; then
        # What python:3.11-slim offers the Dockerfile: Python 3.11 with venv, CA certificates, useradd (passwd).
        mmdebstrap --variant=minbase --include=ca-certificates,python3,python3-venv,passwd bookworm \
            "$WORK/base.tar.part" \
            "deb http://deb.debian.org/debian bookworm main" \
            "deb http://deb.debian.org/debian bookworm-updates main" \
            "deb http://deb.debian.org/debian-security bookworm-security main"
        mv "$WORK/base.tar.part" "$WORK/base.tar"
    fi
    ctr=$(buildah from scratch)
    buildah add "$ctr" "$WORK/base.tar" / >/dev/null
    buildah config --cmd /bin/bash "$ctr"
    buildah commit -q --rm "$ctr" "$BASE_IMAGE"
fi

step "pip configuration of this host, for the build"
# pip inside the build must reach the packages the way the host's pip does (a local wheel of torch, local
# mirrors, an egress CA): the host's settings go into a pip.conf mounted at /etc/pip.conf for the RUN steps only,
# and each local path they name is mounted read-only at the same place. Nothing of it stays in the image.
mkdir -p "$WORK/pip"
python3 -m pip config list \
    | sed -n -E "s/^(:env:|global|install)\.(index-url|extra-index-url|find-links|cert|constraint|trusted-host|default-timeout)='(.*)'$/\2 = \3/p" \
    | awk -F' = ' '!seen[$1]++' | { echo "[global]"; cat; } > "$WORK/pip/pip.conf"
cat "$WORK/pip/pip.conf"
mounts=(-v "$PWD/$WORK/pip/pip.conf:/etc/pip.conf:ro")
for value in $(sed -n -E 's/^(index-url|extra-index-url|find-links|cert|constraint) = //p' "$WORK/pip/pip.conf"); do
    path=${value#file://}
    # A local PEP 503 index (.../simple) links to its files beside it (../../files/...): mount the mirror's root.
    [ "$(basename "$path")" = simple ] && path=$(dirname "$path")
    if [ "${path:0:1}" = / ] && [ -e "$path" ]; then
        mounts+=(-v "$path:$path:ro")
    fi
done

step "build $IMAGE from $dockerfile (buildah bud --isolation chroot)"
# --format docker keeps HEALTHCHECK (OCI image configs have no field for it); --layers reuses unchanged steps.
buildah bud --isolation chroot --format docker --layers -q -f "$dockerfile" -t "$IMAGE" \
    --build-arg BASE_IMAGE="$BASE_IMAGE" --build-arg TORCH_INDEX_URL= --build-arg TORCH_SPEC="$torch_spec" \
    "${mounts[@]}" .

# ------------------------------------------------------------------------------------------- run the image
run=$(mktemp -d "$PWD/$WORK/run.XXXXXX")
containers=()
pids=()
cleanup() {
    local pid ctr
    for pid in "${pids[@]}"; do kill "$pid" 2>/dev/null || true; done
    for pid in "${pids[@]}"; do wait "$pid" 2>/dev/null || true; done
    for ctr in "${containers[@]}"; do buildah rm "$ctr" >/dev/null 2>&1 || true; done
    rm -rf "$run"
}
trap cleanup EXIT
# A fresh container of the image, as `docker run` would make it, named after this run (not in a subshell:
# it records the name for cleanup).
new_container() {
    buildah from --name "$1" "$IMAGE" >/dev/null
    containers+=("$1")
}
# The image runs as uid 1000 (bcf): the folders it writes to are given to that uid, as /data is in the image.
owned_dir() { mkdir -p "$1"; chown 1000:1000 "$1"; }
free_port() { python3 -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])'; }

step "bcf --version in the image"
cli=bcf-check-$$-cli
new_container "$cli"
version=$(buildah run --isolation chroot "$cli" -- bcf --version)
echo "$version"
[[ "$version" == bcf\ * ]] || fail "bcf --version printed '$version'"
buildah run --isolation chroot "$cli" -- python -c \
    'import torch; print(f"torch {torch.__version__}, CUDA build: {torch.version.cuda}")'

step "bcf compress examples/sample --preset fast in the image"
owned_dir "$run/out"
buildah run --isolation chroot -v "$PWD/examples/sample:/opt/bcf/examples/sample:ro" -v "$run/out:/out" "$cli" -- \
    bcf compress /opt/bcf/examples/sample -o /out/sample --preset fast --device cpu
for name in features_0.dds features_1.dds features_2.dds features_3.dds decoder.bin manifest.json report.json; do
    [ -s "$run/out/sample/$name" ] || fail "compress wrote no $name"
done
ls -l "$run/out/sample"

step "compose topology: redis-server, bcf serve and bcf worker in two containers sharing a data folder"
# compose.yaml runs the official redis image; this check runs Debian's redis-server on the host instead, on a
# free loopback port. Chroot isolation shares the host's network, so the containers reach it on 127.0.0.1.
redis_port=$(free_port)
api_port=$(free_port)
mkdir -p "$run/redis"
redis-server --bind 127.0.0.1 --port "$redis_port" --dir "$run/redis" --appendonly yes --save "" \
    >"$run/redis.log" 2>&1 &
pids+=($!)
owned_dir "$run/data"
# Shared data at /farm-data rather than /data: buildah run (1.28) mounts the image's VOLUME /data as an empty
# volume of each container's own, over a `-v` bind mount at the same path.
farm=(--isolation chroot -v "$run/data:/farm-data" --env BCF_DATA_DIR=/farm-data
      --env "BCF_QUEUE_URL=redis://127.0.0.1:$redis_port/0")
api=bcf-check-$$-api
worker=bcf-check-$$-worker
new_container "$api"
new_container "$worker"
buildah run "${farm[@]}" --env "BCF_API_TOKENS=$TOKEN" "$api" -- \
    bcf serve --host 127.0.0.1 --port "$api_port" --workers 0 >"$run/api.log" 2>&1 &
pids+=($!)
buildah run "${farm[@]}" "$worker" -- bcf worker --device cpu >"$run/worker.log" 2>&1 &
pids+=($!)
show_logs() { for log in api worker redis; do echo "--- $log.log"; tail -n 30 "$run/$log.log"; done; }
trap 'show_logs; cleanup' EXIT

url="http://127.0.0.1:$api_port"
auth=(-H "Authorization: Bearer $TOKEN")
for _ in $(seq 120); do
    curl -fsS "$url/healthz" >/dev/null 2>&1 && break
    sleep 1
done
curl -fsS "$url/healthz" || fail "the API did not answer /healthz within 120 s"
echo

json() { python3 -c "import json, sys; print(json.load(sys.stdin)$1)"; }
job=$(curl -fsS "${auth[@]}" -F albedo=@examples/sample/albedo.png -F normal=@examples/sample/normal_gl.png \
    -F arm=@examples/sample/arm.png -F 'options={"preset": "fast"}' "$url/v1/jobs" | json '["id"]')
echo "job $job submitted"
state=queued
for _ in $(seq 300); do
    state=$(curl -fsS "${auth[@]}" "$url/v1/jobs/$job" | json '["state"]')
    case "$state" in succeeded|failed|cancelled) break ;; esac
    sleep 1
done
curl -fsS "${auth[@]}" "$url/v1/jobs/$job"; echo
[ "$state" = succeeded ] || fail "job $job ended '$state' (or did not finish within 300 s)"
curl -fsS "${auth[@]}" -o "$run/artifacts.zip" "$url/v1/jobs/$job/artifacts"
python3 - "$run/artifacts.zip" <<'EOF'
import json, sys, zipfile
with zipfile.ZipFile(sys.argv[1]) as archive:
    assert archive.testzip() is None, "a corrupt member in the artifacts zip"
    names = set(archive.namelist())
    wanted = {"features_0.dds", "features_1.dds", "features_2.dds", "features_3.dds", "decoder.bin",
              "manifest.json", "report.json", "report.html"}
    assert wanted <= names, f"missing from the artifacts zip: {sorted(wanted - names)}"
    report = json.loads(archive.read("report.json"))
print(f"artifacts zip: {len(names)} files, report.json keys: {', '.join(sorted(report)[:6])}, ...")
EOF
trap cleanup EXIT

step "passed: image $IMAGE built and run"
