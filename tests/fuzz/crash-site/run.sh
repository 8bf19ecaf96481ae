#!/usr/bin/env bash
# Checks scripts/fuzz-crash-site.sh (which fuzz failures run-fuzz.sh counts
# as a tolerated library's, tests/fuzz/<harness>.tolerate) on the logs here:
# library-*.log must be put in assimp, ours-*.log in our code. The logs are
# libFuzzer + ASan/UBSan reports of fuzz_asset as they look (library-assimp-segv
# is a real one; library-assimp-heap-corruption is the stack of a CI run on
# 2026-12-03 whose ASan heap was corrupted by assimp's PLY reader and that
# was counted as ours, where the first frame past the runtime was ASan's
# free interceptor; library-assimp-quarantine-check is the CI run of
# 2026-12-05 whose assimp PLY reader overwrote ASan's chunk header, reported
# as a failed CHECK of ASan's allocator, not an "ERROR:"). Run by
# scripts/run-tests.sh.
set -uo pipefail
here=$(cd "$(dirname "$0")" && pwd)
classify="$here/../../../scripts/fuzz-crash-site.sh"
tolerate='libassimp\.so'
bad=0 n=0
for log in "$here"/*.log; do
  name=$(basename "$log")
  n=$((n + 1))
  if bash "$classify" "$log" "$tolerate"; then got=library; else got=ours; fi
  want=${name%%-*}
  if [ "$got" = "$want" ]; then
    echo "ok   $name: $got"
  else
    echo "FAIL $name: put in $got, should be $want"; bad=$((bad + 1))
  fi
  # nothing is a library's when no library is tolerated
  if bash "$classify" "$log" ""; then
    echo "FAIL $name: put in a library with no library tolerated"; bad=$((bad + 1))
  fi
done
[ "$n" -ge 7 ] || { echo "FAIL only $n logs in $here"; exit 1; }
echo "$n logs, $bad wrong"
[ "$bad" -eq 0 ]
