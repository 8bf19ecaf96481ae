#!/usr/bin/env bash
# Runs the layout check, the fuzz crash-site check and every test program
# (tests/unit, tests/hard, tests/integration) against the build in $1
# (default build/). Prints one line per test program and a final
# "N passed, N failed" line; exits non-zero if anything failed.
set -uo pipefail
BUILD=${1:-build}
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
BUILD=$(cd "$BUILD" 2>/dev/null && pwd) || { echo "run-tests: no build directory '$1'" >&2; exit 1; }
export MR_SOURCE_DIR="$ROOT" MR_BUILD_DIR="$BUILD"
LOG_DIR="$BUILD/test-logs"
mkdir -p "$LOG_DIR"
passed=0 failed=0 failed_names=()

run() { # name, command...
  local name=$1; shift
  local log="$LOG_DIR/$name.log" start end
  start=$(date +%s.%N)
  if "$@" >"$log" 2>&1; then
    passed=$((passed + 1)); end=$(date +%s.%N)
    printf "PASS %-34s %6.1fs\n" "$name" "$(awk -v s="$start" -v e="$end" "BEGIN{print e-s}")"
  else
    failed=$((failed + 1)); failed_names+=("$name")
    printf 'FAIL %-34s (log: %s)\n' "$name" "$log"
    tail -n 40 "$log" | sed 's/^/    | /'
  fi
}

# the layout rules a grep can check (a kind is named only in its folder)
mkdir -p "$LOG_DIR/layout"
run layout/check-layout bash scripts/check-layout.sh
# which fuzz failures run-fuzz.sh puts in a tolerated library (stored logs)
mkdir -p "$LOG_DIR/fuzz"
run fuzz/crash-site bash tests/fuzz/crash-site/run.sh

for suite in unit hard integration; do
  mkdir -p "$LOG_DIR/$suite"
  for t in "$BUILD/tests/$suite"/test_*; do
    [ -x "$t" ] || continue
    run "$suite/$(basename "$t")" "$t"
  done
done

if [ $((passed + failed)) -eq 0 ]; then
  echo "run-tests: no test programs under $BUILD/tests" >&2
  exit 1
fi

echo
echo "${passed} passed, ${failed} failed"
[ "$failed" -eq 0 ] || { echo "failed: ${failed_names[*]}"; exit 1; }
