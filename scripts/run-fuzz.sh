#!/usr/bin/env bash
# Runs the libFuzzer harnesses of $1/fuzz/ (make fuzz-build; default build/)
# for $2 seconds each (default 60), or only the harnesses named after that.
# For each harness fuzz_NAME (tests/fuzz/fuzz_NAME.c):
#  1. every file in tests/fuzz/crashers/fuzz_NAME/ is executed once (each is
#     an input that crashed it once and must not any more);
#  2. it fuzzes for the given time from its seeds, tests/fuzz/corpus/fuzz_NAME/
#     (read only), into a working corpus $1/fuzz/work/fuzz_NAME/ that later
#     runs start from; a crash or timeout leaves the input in
#     $1/fuzz/artifacts/fuzz_NAME/.
# libFuzzer options of a harness: tests/fuzz/fuzz_NAME.options (one or more
# per line, # comments). Logs: $1/fuzz/logs/. Prints one line per harness
# (executions, exec/s, coverage: libFuzzer's final "cov:" and "ft:") and
# exits non-zero if any crasher or fuzz run failed. docs/fuzzing.md.
set -uo pipefail
BUILD=${1:-build}
TIME=${2:-60}
shift $(( $# < 2 ? $# : 2 ))
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
FUZZ=$(cd "$BUILD/fuzz" 2>/dev/null && pwd) || { echo "run-fuzz: no $BUILD/fuzz (make fuzz-build)" >&2; exit 1; }
mkdir -p "$FUZZ/logs" "$FUZZ/work" "$FUZZ/artifacts"
passed=0 failed=0 failed_names=()

names=("$@")
if [ ${#names[@]} -eq 0 ]; then
  for src in tests/fuzz/fuzz_*.c; do names+=("$(basename "$src" .c)"); done
fi

fail() { # name, log, what
  failed=$((failed + 1)); failed_names+=("$1")
  printf 'FAIL %-24s %s (log: %s)\n' "fuzz/$1" "$3" "$2"
  grep -E '^(==[0-9]+==ERROR|SUMMARY|.*runtime error|artifact_prefix|Test unit written|fuzz_[a-z_]*: )' "$2" |
    head -n 12 | sed 's/^/    | /'
  tail -n 25 "$2" | sed 's/^/    | /'
}

for name in "${names[@]}"; do
  bin="$FUZZ/$name"
  if [ ! -x "$bin" ]; then
    failed=$((failed + 1)); failed_names+=("$name")
    echo "FAIL fuzz/$name: no $bin (make fuzz-build)"
    continue
  fi
  opts=()
  if [ -f "tests/fuzz/$name.options" ]; then
    read -r -a opts <<<"$(sed 's/#.*//' "tests/fuzz/$name.options" | tr '\n' ' ')"
  fi

  # 1. the crashers found so far: each must now run clean
  crashers=()
  if [ -d "tests/fuzz/crashers/$name" ]; then
    while IFS= read -r f; do crashers+=("$f"); done < <(find "tests/fuzz/crashers/$name" -type f ! -name '*.md' | sort)
  fi
  if [ ${#crashers[@]} -gt 0 ]; then
    log="$FUZZ/logs/$name.crashers.log"
    if ! "$bin" "${opts[@]}" "${crashers[@]}" >"$log" 2>&1; then
      fail "$name" "$log" "a crasher of tests/fuzz/crashers/$name crashes again"
      continue
    fi
  fi

  # 2. fuzz
  log="$FUZZ/logs/$name.log"
  mkdir -p "$FUZZ/work/$name" "$FUZZ/artifacts/$name"
  seeds=()
  [ -d "tests/fuzz/corpus/$name" ] && seeds+=("tests/fuzz/corpus/$name")
  start=$(date +%s)
  "$bin" "${opts[@]}" -max_total_time="$TIME" -print_final_stats=1 \
    -artifact_prefix="$FUZZ/artifacts/$name/" "$FUZZ/work/$name" "${seeds[@]}" >"$log" 2>&1
  rc=$?
  end=$(date +%s)
  if [ $rc -ne 0 ]; then
    fail "$name" "$log" "libFuzzer exit $rc after $((end - start)) s; the input is in $FUZZ/artifacts/$name/"
    continue
  fi
  # "#1234567	DONE   cov: 812 ft: 3400 corp: 310/52Kb lim: 4096 exec/s: 20576 rss: 61Mb"
  done_line=$(grep -E '^#[0-9]+[[:space:]]+DONE' "$log" | tail -n 1)
  runs=$(grep -oE 'stat::number_of_executed_units:[[:space:]]+[0-9]+' "$log" | grep -oE '[0-9]+$')
  rate=$(grep -oE 'stat::average_exec_per_sec:[[:space:]]+[0-9]+' "$log" | grep -oE '[0-9]+$')
  rss=$(grep -oE 'stat::peak_rss_mb:[[:space:]]+[0-9]+' "$log" | grep -oE '[0-9]+$')
  cov=$(sed -nE 's/.* cov: ([0-9]+).*/\1/p' <<<"$done_line")
  ft=$(sed -nE 's/.* ft: ([0-9]+).*/\1/p' <<<"$done_line")
  corp=$(sed -nE 's/.* corp: ([0-9]+)\/.*/\1/p' <<<"$done_line")
  passed=$((passed + 1))
  printf 'PASS %-24s %4ss %10s execs %7s exec/s  cov: %-5s ft: %-6s corpus %-5s rss %s MB  crashers re-run: %d\n' \
    "fuzz/$name" "$((end - start))" "${runs:-?}" "${rate:-?}" "${cov:-?}" "${ft:-?}" "${corp:-?}" "${rss:-?}" "${#crashers[@]}"
done

echo
echo "fuzz: ${passed} passed, ${failed} failed (${TIME} s each)"
[ "$failed" -eq 0 ] || { echo "failed: ${failed_names[*]}"; exit 1; }
