#!/usr/bin/env bash
# make run: renders examples/skinned-walk.json into out/skinned-walk/ with the
# one-shot renderer and prints where the frames and statistics are.
set -euo pipefail
BUILD=${1:-build}
cd "$(dirname "$0")/.."
OUT=out/skinned-walk
"$BUILD"/microrayd render examples/skinned-walk.json --out "$OUT"
echo "frames: $OUT/0000.exr .. ; statistics: $OUT/stats.json"
