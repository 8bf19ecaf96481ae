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
# per line, # comments). tests/fuzz/fuzz_NAME.tolerate names libraries whose
# own crashes are not failures (assimp): such a crash, timeout or OOM is
# logged, its input kept in $1/fuzz/library-crashes/fuzz_NAME/, and fuzzing
# goes on for the time left; a crash in our code still fails. Crashers in
# tests/fuzz/crashers/fuzz_NAME/library/ must crash only in such a library
# (or not at all). Logs: $1/fuzz/logs/. Prints one line per harness
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
  grep -E '^(==[0-9]+== ?ERROR|SUMMARY|.*runtime error|artifact_prefix|Test unit written|fuzz_[a-z_]*: )' "$2" |
    head -n 12 | sed 's/^/    | /'
  tail -n 25 "$2" | sed 's/^/    | /'
}

# Whether the failure in log $1 happened inside a library matching the
# extended regex $2 (scripts/fuzz-crash-site.sh).
library_crash() { bash scripts/fuzz-crash-site.sh "$1" "$2"; }

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

  tolerate=""
  [ -f "tests/fuzz/$name.tolerate" ] && tolerate=$(sed 's/#.*//' "tests/fuzz/$name.tolerate" | grep -v '^[[:space:]]*$' | paste -sd'|')

  # 1. the crashers found so far: each must now run clean
  crashers=() lib_crashers=()
  if [ -d "tests/fuzz/crashers/$name" ]; then
    while IFS= read -r f; do crashers+=("$f"); done < <(find "tests/fuzz/crashers/$name" -maxdepth 1 -type f ! -name '*.md' | sort)
    if [ -d "tests/fuzz/crashers/$name/library" ]; then
      while IFS= read -r f; do lib_crashers+=("$f"); done < <(find "tests/fuzz/crashers/$name/library" -type f ! -name '*.md' | sort)
    fi
  fi
  if [ ${#crashers[@]} -gt 0 ]; then
    log="$FUZZ/logs/$name.crashers.log"
    if ! "$bin" "${opts[@]}" "${crashers[@]}" >"$log" 2>&1; then
      fail "$name" "$log" "a crasher of tests/fuzz/crashers/$name crashes again"
      continue
    fi
  fi
  bad=""
  for f in "${lib_crashers[@]}"; do
    log="$FUZZ/logs/$name.library-crasher.log"
    if ! "$bin" "${opts[@]}" "$f" >"$log" 2>&1 && ! library_crash "$log" "$tolerate"; then
      bad=$f
      break
    fi
  done
  if [ -n "$bad" ]; then
    fail "$name" "$log" "$bad now crashes outside ${tolerate:-the tolerated libraries}"
    continue
  fi

  # 2. fuzz (again for the time left after a tolerated library crash)
  log="$FUZZ/logs/$name.log"
  mkdir -p "$FUZZ/work/$name" "$FUZZ/artifacts/$name"
  seeds=()
  [ -d "tests/fuzz/corpus/$name" ] && seeds+=("tests/fuzz/corpus/$name")
  start=$(date +%s)
  : >"$FUZZ/logs/$name.all.log"
  lib_crashes=0 runs_total=0 rc=0
  while :; do
    left=$((TIME - ($(date +%s) - start)))
    [ $left -ge 1 ] || { rc=0; break; }
    "$bin" "${opts[@]}" -max_total_time="$left" -print_final_stats=1 \
      -artifact_prefix="$FUZZ/artifacts/$name/" "$FUZZ/work/$name" "${seeds[@]}" >"$log" 2>&1
    rc=$?
    cat "$log" >>"$FUZZ/logs/$name.all.log"
    # (libFuzzer can print its final stats twice, e.g. once per worker
    # thread's exit: the last figure counts)
    r=$(grep -oE 'stat::number_of_executed_units:[[:space:]]+[0-9]+' "$log" | grep -oE '[0-9]+$' | tail -n 1)
    runs_total=$((runs_total + ${r:-0}))
    [ $rc -ne 0 ] && [ -n "$tolerate" ] && library_crash "$log" "$tolerate" || break
    lib_crashes=$((lib_crashes + 1))
    mkdir -p "$FUZZ/library-crashes/$name"
    unit=$(sed -nE 's/.*Test unit written to (.*)$/\1/p' "$log" | tail -n 1)
    [ -n "$unit" ] && [ -f "$unit" ] && mv "$unit" "$FUZZ/library-crashes/$name/"
    cp "$log" "$FUZZ/library-crashes/$name/$(basename "${unit:-unknown}").log"
  done
  end=$(date +%s)
  if [ $rc -ne 0 ]; then
    fail "$name" "$log" "libFuzzer exit $rc after $((end - start)) s; the input is in $FUZZ/artifacts/$name/"
    continue
  fi
  # "#1234567	DONE   cov: 812 ft: 3400 corp: 310/52Kb lim: 4096 exec/s: 20576 rss: 61Mb"
  # (the last status line of all runs, when the last one ended in a library crash)
  done_line=$(grep -E '^#[0-9]+[[:space:]]+DONE' "$log" | tail -n 1)
  [ -n "$done_line" ] || done_line=$(grep -E '^#[0-9]+[[:space:]].* cov: ' "$FUZZ/logs/$name.all.log" | tail -n 1)
  runs=$runs_total
  rate=$((runs_total / (end - start > 0 ? end - start : 1)))
  rss=$(grep -oE 'stat::peak_rss_mb:[[:space:]]+[0-9]+' "$log" | grep -oE '[0-9]+$' | tail -n 1)
  cov=$(sed -nE 's/.* cov: ([0-9]+).*/\1/p' <<<"$done_line")
  ft=$(sed -nE 's/.* ft: ([0-9]+).*/\1/p' <<<"$done_line")
  corp=$(sed -nE 's/.* corp: ([0-9]+)\/.*/\1/p' <<<"$done_line")
  passed=$((passed + 1))
  extra=""
  [ $lib_crashes -gt 0 ] && extra="  library crashes: $lib_crashes (in $FUZZ/library-crashes/$name/)"
  printf 'PASS %-24s %4ss %10s execs %7s exec/s  cov: %-5s ft: %-6s corpus %-5s rss %s MB  crashers re-run: %d%s\n' \
    "fuzz/$name" "$((end - start))" "${runs:-?}" "${rate:-?}" "${cov:-?}" "${ft:-?}" "${corp:-?}" "${rss:-?}" \
    "$((${#crashers[@]} + ${#lib_crashers[@]}))" "$extra"
done

echo
echo "fuzz: ${passed} passed, ${failed} failed (${TIME} s each)"
[ "$failed" -eq 0 ] || { echo "failed: ${failed_names[*]}"; exit 1; }
