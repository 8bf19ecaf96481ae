#!/usr/bin/env bash
# Prints the benchmark table (make bench) and writes bench/report.md with
# its plots (bench/report.sh: speed against error per kind). Benchmarks
# report figures; they never fail on a time.
set -euo pipefail
BUILD=${1:-build}
cd "$(dirname "$0")/.."
export MR_BUILD_DIR="$BUILD"
data=$BUILD/bench-data
rm -rf "$data"
mkdir -p "$data"
export MR_BENCH_DATA=$data
for b in "$BUILD"/bench/*; do
  [ -x "$b" ] && "$b" "${@:2}"
done | tee "$data/bench.log"
bash bench/report.sh "$data/points.tsv" "$data/bench.log" bench
