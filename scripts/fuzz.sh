#!/usr/bin/env bash
# The fuzz harness (fuzz/): coverage-guided libFuzzer on volux's input readers (EXR/HDR/PNG/JPEG,
# training configs, poses.csv, checkpoint state). Usage: scripts/fuzz.sh [SECONDS_PER_TARGET]
# (default 150, i.e. 10 minutes for the four targets). Crashes land in fuzz/artifacts/<target>/;
# the script exits non-zero if any target found one. Results and the last run: docs/limits.md.
#
# Needs `cargo install cargo-fuzz`. cargo-fuzz passes nightly-only flags to rustc, so on the
# stable toolchain RUSTC_BOOTSTRAP=1 lets them through; no sanitizer is used (`-s none`):
# panics, aborts (an allocation that fails), arithmetic overflow (debug assertions are on) and
# timeouts are what is caught, and -rss_limit_mb bounds memory.
set -euo pipefail
cd "$(dirname "$0")/.."
seconds="${1:-150}"
export RUSTC_BOOTSTRAP=1
python3 scripts/fuzz_seeds.py fuzz/corpus-seeds
cd fuzz
cargo fuzz build -s none
status=0
for target in image_readers train_config poses_csv checkpoint_state; do
  mkdir -p "corpus/$target" "artifacts/$target"
  echo "== $target: ${seconds}s"
  if ! cargo fuzz run -s none "$target" "corpus/$target" "corpus-seeds/$target" -- \
      -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 -max_len=65536 \
      -print_final_stats=1 2>&1 | tail -n 25; then
    status=1
  fi
done
exit $status
