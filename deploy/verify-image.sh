#!/usr/bin/env bash
# Builds deploy/Dockerfile unchanged and runs the image for real (podman, or docker):
#   1. where the registry cannot be reached, makes local stand-ins for the two base images and
#      says so: debian:bookworm-slim from debootstrap, and the builder image rust:1.95-slim-bookworm
#      from it plus the Rust toolchain that builds the project on this host (and gcc);
#   2. builds the image (timed), starts it with the shipped models inside, waits for SERVING
#      through this host's `alignist health`, sends a real Predict with `alignist predict` and
#      checks the answer, checks the server runs as a non-root uid, stops it with SIGTERM and
#      checks it exits 0 within the drain time;
#   3. prints the image size and the build time. Exits 0 only if all of that held.
# Usage: bash deploy/verify-image.sh      (not part of `cargo test`: the build takes ~15 minutes)
set -euo pipefail
cd "$(dirname "$0")/.."
IMAGE=alignist:verify
NAME=alignist-verify
PORT=${PORT:-50061}
DRAIN_S=20
WORK=$(mktemp -d /tmp/alignist-verify.XXXXXX)
trap 'podman rm -f "$NAME" >/dev/null 2>&1 || true; rm -rf "$WORK"' EXIT
say() { echo "verify-image: $*"; }

# podman on these machines needs runc and cgroupfs, and rlimits it can set.
PODMAN=(podman --runtime runc --cgroup-manager cgroupfs)
LIMITS=(--ulimit nofile=1024:1024 --ulimit nproc=4096:4096)
if ! command -v podman >/dev/null || ! command -v debootstrap >/dev/null; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null; then
    say "installing podman, runc and debootstrap (apt-get)"
    apt-get install -y podman runc debootstrap >/dev/null
  else
    say "podman, runc and debootstrap are needed (apt-get install -y podman runc debootstrap)"
    exit 1
  fi
fi

# The host's client and a test image.
cargo build --release --bin alignist --bin alignist-train
./target/release/alignist-train render --shape cube --count 1 --size 64 --seed 5 --out "$WORK/data" >/dev/null
PNG=$(find "$WORK/data" -name '*.png' -path '*rgb*' | head -1)

# 1. Base images.
if ! "${PODMAN[@]}" image exists docker.io/library/debian:bookworm-slim; then
  if timeout 60 "${PODMAN[@]}" pull -q docker.io/library/debian:bookworm-slim >/dev/null 2>&1; then
    say "pulled debian:bookworm-slim"
  else
    say "registry unreachable: making a local stand-in for debian:bookworm-slim with debootstrap"
    debootstrap --variant=minbase bookworm "$WORK/rootfs" >/dev/null
    tar -C "$WORK/rootfs" -c . | "${PODMAN[@]}" import - docker.io/library/debian:bookworm-slim >/dev/null
    rm -rf "$WORK/rootfs"
  fi
fi
if ! "${PODMAN[@]}" image exists docker.io/library/rust:1.95-slim-bookworm; then
  if timeout 60 "${PODMAN[@]}" pull -q docker.io/library/rust:1.95-slim-bookworm >/dev/null 2>&1; then
    say "pulled rust:1.95-slim-bookworm"
  else
    say "registry unreachable: making a local stand-in for rust:1.95-slim-bookworm (debian stand-in + this host's Rust $(rustc --version | cut -d' ' -f2) + gcc)"
    SYSROOT=$(rustc --print sysroot)
    mkdir -p "$WORK/builder/rust"
    cp -a "$SYSROOT/bin" "$SYSROOT/lib" "$WORK/builder/rust/"
    # This host's CA bundle too, so that cargo reaches the registry through the same TLS path
    # (a proxy's certificate authority) as the host's cargo does.
    cp /etc/ssl/certs/ca-certificates.crt "$WORK/builder/host-ca.crt"
    cat > "$WORK/builder/Containerfile" <<'EOF'
FROM docker.io/library/debian:bookworm-slim
RUN apt-get update && apt-get install -y --no-install-recommends gcc libc6-dev ca-certificates \
 && rm -rf /var/lib/apt/lists/*
COPY host-ca.crt /etc/ssl/certs/ca-certificates.crt
COPY rust /usr/local/rust
ENV PATH=/usr/local/rust/bin:$PATH CARGO_HOME=/usr/local/cargo
EOF
    "${PODMAN[@]}" build --pull=never --network host "${LIMITS[@]}" \
      -t docker.io/library/rust:1.95-slim-bookworm "$WORK/builder" >/dev/null
  fi
fi

# 2. The image, from deploy/Dockerfile as it is.
start=$(date +%s)
"${PODMAN[@]}" build --pull=never --network host "${LIMITS[@]}" -f deploy/Dockerfile -t "$IMAGE" . \
  > "$WORK/build.log" 2>&1 || { tail -30 "$WORK/build.log"; say "FAILED: the build"; exit 1; }
build_s=$(( $(date +%s) - start ))
size_mb=$(( $("${PODMAN[@]}" image inspect --format '{{.Size}}' "$IMAGE") / 1000000 ))
say "built $IMAGE in ${build_s} s, ${size_mb} MB"

"${PODMAN[@]}" run -d --name "$NAME" --network host "${LIMITS[@]}" \
  -e ALIGNIST_LISTEN=127.0.0.1:$PORT -e ALIGNIST_METRICS_LISTEN=off \
  -e ALIGNIST_DRAIN_TIMEOUT_S=$DRAIN_S "$IMAGE" >/dev/null
CLI=(./target/release/alignist --server "http://127.0.0.1:$PORT" --timeout-s 5)
serving=no
for _ in $(seq 1 120); do
  if "${CLI[@]}" health --service alignist.v1.Alignist >/dev/null 2>&1; then serving=yes; break; fi
  sleep 1
done
[ "$serving" = yes ] || { "${PODMAN[@]}" logs "$NAME" | tail -20; say "FAILED: never SERVING"; exit 1; }
say "the container is SERVING"

answer=$("${CLI[@]}" predict --image "$PNG" --top-k 3 --json)
top=$(echo "$answer" | python3 -c 'import json,sys; a=json.load(sys.stdin); print(len(a["top"]), a["model"])')
[ "${top%% *}" = 3 ] || { echo "$answer"; say "FAILED: Predict did not answer 3 rotations"; exit 1; }
say "Predict answered 3 rotations from model ${top#* }"

uid=$("${PODMAN[@]}" exec "$NAME" id -u)
[ "$uid" != 0 ] || { say "FAILED: the server runs as root"; exit 1; }
say "the server runs as uid $uid"

start=$(date +%s)
"${PODMAN[@]}" stop -t $((DRAIN_S + 10)) "$NAME" >/dev/null
stop_s=$(( $(date +%s) - start ))
code=$("${PODMAN[@]}" inspect --format '{{.State.ExitCode}}' "$NAME")
[ "$code" = 0 ] && [ "$stop_s" -le "$DRAIN_S" ] || { say "FAILED: exit code $code after ${stop_s} s"; exit 1; }
say "OK: image ${size_mb} MB built in ${build_s} s; SERVING, answered a Predict, ran as uid $uid, exited 0 ${stop_s} s after SIGTERM"
