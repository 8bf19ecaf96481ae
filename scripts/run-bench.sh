#!/usr/bin/env bash
# Prints the benchmark table (make bench). Benchmarks report figures; they
# never fail on a time.
set -euo pipefail
BUILD=${1:-build}
cd "$(dirname "$0")/.."
export MR_BUILD_DIR="$BUILD"
for b in "$BUILD"/bench/*; do
  [ -x "$b" ] && "$b" "${@:2}"
done
