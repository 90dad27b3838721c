#!/usr/bin/env bash
# Measures training on a GPU with the wgpu backend (docs/performance.md):
#   1. builds `volux` with `--features wgpu` (or uses VOLUX_BIN),
#   2. checks that wgpu finds a GPU and agrees with the CPU (`volux backend --backend wgpu`),
#   3. runs `volux train bench` on configs/quickstart.toml for stage 1 and stage 2,
#   4. trains configs/synthetic64.toml (data made on the fly) for TRAIN_MINUTES minutes,
# and writes everything to one folder: the argument, else $OUT, else runs/gpu-bench.
#
#   scripts/gpu-bench.sh [OUT_DIR]
#
# Environment (all optional):
#   TRAIN_MINUTES=10       minutes of synthetic64 training (0 skips it)
#   BENCH_STEPS=5          measured steps per bench stage
#   VOLUX_BIN=path         a prebuilt binary with the wgpu feature; skips the build
#   CARGO_OFFLINE=1        build with `cargo --offline` (a machine without internet needs the
#                          dependencies already in its cargo home, or vendored)
#   CUBECL_WGPU_DEFAULT_DEVICE=DiscreteGpu(0)   the adapter wgpu must use; the default
#                          refuses software adapters, so a machine without a GPU fails here
#                          instead of measuring a CPU emulation
set -euo pipefail

cd "$(dirname "${BASH_SOURCE[0]}")/.."
OUT_DIR="${1:-${OUT:-runs/gpu-bench}}"
TRAIN_MINUTES="${TRAIN_MINUTES:-10}"
BENCH_STEPS="${BENCH_STEPS:-5}"
export CUBECL_WGPU_DEFAULT_DEVICE="${CUBECL_WGPU_DEFAULT_DEVICE:-DiscreteGpu(0)}"
mkdir -p "$OUT_DIR"
OUT_DIR="$(cd "$OUT_DIR" && pwd)"
LOG="$OUT_DIR/gpu-bench.log"
: >"$LOG"

say() { echo "[gpu-bench $(date +%H:%M:%S)] $*" | tee -a "$LOG" >&2; }
fail() {
    say "FAILED: $*"
    exit 1
}
# `step NAME SECONDS CMD...`: runs CMD with a time limit, output to the log and NAME.txt.
step() {
    local name="$1" limit="$2"
    shift 2
    say "$name: $* (limit ${limit}s)"
    local status=0
    timeout --kill-after=30 "$limit" "$@" 2>&1 | tee "$OUT_DIR/$name.txt" >>"$LOG" || status=$?
    if [ "$status" -eq 124 ] || [ "$status" -eq 137 ]; then
        fail "$name ran past ${limit}s (see $OUT_DIR/$name.txt)"
    elif [ "$status" -ne 0 ]; then
        fail "$name exited with $status (see $OUT_DIR/$name.txt)"
    fi
}

{
    echo "date: $(date -u +%Y-%m-%dT%H:%M:%SZ)"
    echo "commit: $(git rev-parse --short HEAD 2>/dev/null || echo unknown)"
    echo "cpu: $(lscpu 2>/dev/null | sed -n 's/^Model name: *//p' | head -n1), $(nproc) cores"
    echo "load: $(uptime)"
    if command -v nvidia-smi >/dev/null; then
        nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader
    else
        echo "nvidia-smi: not found"
    fi
} >"$OUT_DIR/machine.txt" 2>&1
cat "$OUT_DIR/machine.txt" >>"$LOG"

if [ -n "${VOLUX_BIN:-}" ]; then
    BIN="$VOLUX_BIN"
else
    offline=()
    if [ "${CARGO_OFFLINE:-0}" = 1 ]; then offline=(--offline); fi
    step build 1800 cargo build --release --features wgpu "${offline[@]}"
    BIN="${CARGO_TARGET_DIR:-target}/release/volux"
fi
[ -x "$BIN" ] || fail "no binary at $BIN"

step backend-check 300 "$BIN" backend --backend wgpu
grep -q "^wgpu: ok" "$OUT_DIR/backend-check.txt" ||
    fail "wgpu found no usable GPU adapter (see $OUT_DIR/backend-check.txt)"

for stage in 1 2; do
    step "bench-stage$stage" 600 "$BIN" train bench --config configs/quickstart.toml \
        --stage "$stage" --steps "$BENCH_STEPS" --backend wgpu \
        --out "$OUT_DIR/quickstart-stage$stage-wgpu.md"
done

if [ "$TRAIN_MINUTES" != 0 ]; then
    # synthetic64 reads a prebuilt example cache; here the heads are rendered on the fly
    # (no [data.cache]) and the run stops itself after TRAIN_MINUTES ([output] minutes).
    # The config keeps its folder depth so that its relative paths stay inside OUT_DIR.
    mkdir -p "$OUT_DIR/configs"
    config="$OUT_DIR/configs/synthetic64-live.toml"
    awk -v minutes="$TRAIN_MINUTES" '
        /^\[/ { skip = ($0 == "[data.cache]") }
        skip { next }
        /^minutes *=/ { next }
        { print }
        $0 == "[output]" { print "minutes = " minutes }
    ' configs/synthetic64.toml >"$config"
    limit=$((TRAIN_MINUTES * 60 + 300))
    step train "$limit" "$BIN" train --config "$config" --backend wgpu \
        --out "$OUT_DIR/synthetic64"
    cp "$OUT_DIR/synthetic64/metrics.jsonl" "$OUT_DIR/metrics.jsonl"
    grid="$(ls "$OUT_DIR"/synthetic64/grids/grid-*.png 2>/dev/null | sort | tail -n1)"
    [ -n "$grid" ] || fail "training wrote no sample grid"
    cp "$grid" "$OUT_DIR/last-grid.png"
fi

say "done: $OUT_DIR"
ls -l "$OUT_DIR" | tee -a "$LOG" >&2
