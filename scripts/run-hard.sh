#!/usr/bin/env bash
# Runs the hard-case programs $1/tests/hard/test_* (default build/check, where
# `make hard` builds them with AddressSanitizer, LeakSanitizer and
# UndefinedBehaviorSanitizer) one after the other, or only the programs named
# after $1, and prints a report in markdown (also written to $1/hard-report.md):
#  - per kind (the HARD_KIND of each program), a table of every hard case with
#    the figures it measured and the tolerance each is held to: the HARD lines
#    the cases print through tests/support/hard_report.h;
#  - per program: its cases, failures, whether a sanitizer reported anything
#    (a leak, an invalid access, undefined behaviour; "not built in" when the
#    program was built without ASan) and whether a NaN or Inf was met (a
#    figure of type "nan" above 0, or a figure that is itself not finite).
# Exits non-zero when a program exits non-zero, a case fails or crashes, a
# figure is outside its tolerance, a sanitizer reports, or a case passes
# without reporting any figure. Logs: $1/hard-logs/.
set -uo pipefail
BUILD=${1:-build/check}
shift $(( $# < 1 ? $# : 1 ))
ROOT=$(cd "$(dirname "$0")/.." && pwd)
cd "$ROOT"
BUILD=$(cd "$BUILD" 2>/dev/null && pwd) || { echo "run-hard: no build directory '$BUILD' (make hard)" >&2; exit 1; }
export MR_SOURCE_DIR="$ROOT" MR_BUILD_DIR="$BUILD"
# LeakSanitizer on (the default with ASan on Linux, said so in case the
# environment turned it off); cmocka's own format on stdout, which is parsed.
export ASAN_OPTIONS="${ASAN_OPTIONS:+$ASAN_OPTIONS:}detect_leaks=1"
export UBSAN_OPTIONS="${UBSAN_OPTIONS:+$UBSAN_OPTIONS:}print_stacktrace=1"
export CMOCKA_MESSAGE_OUTPUT=STDOUT
LOG_DIR="$BUILD/hard-logs"
mkdir -p "$LOG_DIR"
RECORDS="$LOG_DIR/records.tsv"
: >"$RECORDS"

programs=()
if [ $# -gt 0 ]; then
  for name in "$@"; do programs+=("$BUILD/tests/hard/$name"); done
else
  for t in "$BUILD"/tests/hard/test_*; do
    [ -x "$t" ] && [ ! -d "$t" ] && programs+=("$t")
  done
fi
if [ ${#programs[@]} -eq 0 ]; then
  echo "run-hard: no hard-case programs under $BUILD/tests/hard (make hard builds them)" >&2
  exit 1
fi

start_all=$(date +%s.%N)
for t in "${programs[@]}"; do
  name=$(basename "$t")
  log="$LOG_DIR/$name.log"
  if [ ! -x "$t" ]; then
    printf 'PROG\t%s\t127\t0\tno such program\tno\n' "$name" >>"$RECORDS"
    continue
  fi
  echo "run-hard: $name" >&2
  start=$(date +%s.%N)
  "$t" >"$log" 2>&1
  rc=$?
  end=$(date +%s.%N)
  seconds=$(awk -v s="$start" -v e="$end" 'BEGIN { printf "%.1f", e - s }')
  asan=no
  grep -q __asan_init "$t" 2>/dev/null && asan=yes
  # the first line of each sanitizer report
  sanitizer=$(grep -E 'ERROR: (AddressSanitizer|LeakSanitizer)|runtime error:|SUMMARY: UndefinedBehaviorSanitizer' "$log" |
              head -n 3 | sed -E 's/^==[0-9]+==//; s/ on address .*//; s/[[:space:]]+/ /g' | paste -sd ';' -)
  printf 'PROG\t%s\t%d\t%s\t%s\t%s\n' "$name" "$rc" "$seconds" "$sanitizer" "$asan" >>"$RECORDS"
  # cases (cmocka's status lines, the failure message before a FAILED) and
  # figures (hard_report.h's HARD lines)
  awk -v prog="$name" -F'\t' '
    function flush_run() { if (running != "") { printf "CASE\t%s\t%s\tcrashed\t%s\n", prog, running, msg; running = "" } }
    /^HARD\t/ { printf "FIG\t%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\t%s\n", prog, $2, $3, $4, $5, $6, $7, $8, $9; next }
    /^\[ RUN +\] / { flush_run(); running = $0; sub(/^\[ RUN +\] /, "", running); msg = ""; prev = ""; next }
    # a failure: cmocka prints fail_msg texts as "ERROR: text", an assertion
    # as its expression or values, then "[   LINE   ] --- file:line: error"
    /^ERROR: / { if (msg == "") { msg = $0; sub(/^ERROR: /, "", msg) } next }
    /\[   LINE   \] --- / {
      loc = $0; sub(/.*\[   LINE   \] --- /, "", loc); sub(/: error:.*/, "", loc)
      if (msg == "") msg = (prev != "" ? prev " " : "") "at " loc
      gsub(/\t/, " ", msg); next
    }
    { prev = $0; sub(/^\[ +ERROR +\] --- /, "", prev) }
    /^\[ +(OK|FAILED|SKIPPED) +\] [A-Za-z_][A-Za-z0-9_]*$/ {
      status = $0; sub(/^\[ +/, "", status); sub(/ .*/, "", status)
      c = $0; sub(/^\[[^]]*\] /, "", c)
      if (c == running) { printf "CASE\t%s\t%s\t%s\t%s\n", prog, c, status, msg; running = "" }
      next
    }
    END { flush_run() }
  ' "$log" >>"$RECORDS"
done
end_all=$(date +%s.%N)
total=$(awk -v s="$start_all" -v e="$end_all" 'BEGIN { printf "%.0f", e - s }')

REPORT="$BUILD/hard-report.md"
awk -F'\t' -v total="$total" -v date="$(date -u '+%Y-%m-%d %H:%M UTC')" -v host="$(uname -n), $(nproc) cores" '
  function num(v) { return v == v + 0 }
  function fmt(v) {
    if (!num(v)) return v
    if (v == int(v) && v < 1e15 && v > -1e15) return sprintf("%d", v)
    return sprintf("%.4g", v)
  }
  function cell(s) { gsub(/\|/, "\\|", s); return s }
  $1 == "PROG" {
    np++; pname[np] = $2; prc[$2] = $3; psec[$2] = $4; psan[$2] = $5; pasan[$2] = $6; next
  }
  $1 == "CASE" {
    nc++; cprog[nc] = $2; cname[nc] = $3; cstat[nc] = $4; cmsg[nc] = $5
    ncases[$2]++
    if ($4 != "OK" && $4 != "SKIPPED") nfailed[$2]++
    next
  }
  $1 == "FIG" {
    nf++; fprog[nf] = $2; fkind[nf] = $3; fcase[nf] = $4; ftype[nf] = $5; ffig[nf] = $6
    fval[nf] = $7; fop[nf] = $8; fbound[nf] = $9; fres[nf] = $10
    key = $2 SUBSEP $4; nfig[key]++
    nfigs[$2]++
    if (!($2 in pkind)) pkind[$2] = $3
    if (!($3 in seen_kind)) { seen_kind[$3] = 1; kinds[++nk] = $3 }
    v = $7 + 0
    if (($5 == "nan" && v != 0) || $7 ~ /nan|inf/) nan_met[$2] = nan_met[$2] (nan_met[$2] == "" ? "" : "; ") $4 ": " $6
    if ($10 != "ok") bad_fig[$2]++
    next
  }
  END {
    printf "# Hard cases (make hard)\n\n%s, %s; %d programs under ASan + UBSan, %s s.\n", date, host, np, total
    printf "Each figure is what the case measured and asserted; the tolerance is the bound it is held to.\n"
    for (p = 1; p <= np; p++) if (!(pname[p] in pkind)) { pkind[pname[p]] = "(no figures)"; if (!("(no figures)" in seen_kind)) { seen_kind["(no figures)"] = 1; kinds[++nk] = "(no figures)" } }
    for (k = 1; k <= nk; k++) {
      printf "\n## %s\n\n| case | type | figure | measured | tolerance | result |\n|---|---|---|---|---|---|\n", kinds[k]
      for (c = 1; c <= nc; c++) {
        if (pkind[cprog[c]] != kinds[k]) continue
        first = 1; label = cname[c]
        for (f = 1; f <= nf; f++) {
          if (fprog[f] != cprog[c] || fcase[f] != cname[c]) continue
          m = fmt(fval[f]); b = fmt(fbound[f])
          if (m == b && fval[f] != fbound[f]) { m = sprintf("%.9g", fval[f]); b = sprintf("%.9g", fbound[f]) }
          printf "| %s | %s | %s | %s | %s %s | %s |\n", first ? label : "", ftype[f], cell(ffig[f]), m, fop[f], b, fres[f]
          first = 0
        }
        if (cstat[c] == "OK" && first) {
          printf "| %s | | (no figure reported) | | | FAIL |\n", label; nofig++; nofig_list = nofig_list " " cname[c]
        } else if (cstat[c] != "OK" && cstat[c] != "SKIPPED") {
          printf "| %s | | (case %s%s) | | | FAIL |\n", first ? label : "", tolower(cstat[c]), cmsg[c] != "" ? ": " cell(cmsg[c]) : ""
        } else if (cstat[c] == "SKIPPED") {
          printf "| %s | | (skipped) | | | skipped |\n", first ? label : ""
        }
      }
    }
    printf "\n## Programs\n\n| program | kind | cases | failed | figures | sanitizers | NaN/Inf met | exit | seconds |\n|---|---|---|---|---|---|---|---|---|\n"
    for (p = 1; p <= np; p++) {
      n = pname[p]
      san = psan[n] != "" ? psan[n] : (pasan[n] == "yes" ? "clean" : "not built in")
      nm = nan_met[n] != "" ? "yes: " nan_met[n] : "no"
      printf "| %s | %s | %d | %d | %d | %s | %s | %d | %s |\n", n, pkind[n], ncases[n], nfailed[n], nfigs[n], cell(san), cell(nm), prc[n], psec[n]
      cases += ncases[n]; failed += nfailed[n]; figs += nfigs[n]; badf += bad_fig[n]
      if (prc[n] != 0) bad_exit = bad_exit " " n
      if (psan[n] != "") bad_san = bad_san " " n
    }
    printf "\n%d programs, %d cases, %d figures: ", np, cases, figs
    if (failed + badf + nofig == 0 && bad_exit == "" && bad_san == "") { printf "every figure within its tolerance, sanitizers clean.\n"; exit 0 }
    printf "FAILED"
    if (failed) printf "; %d cases failed or crashed", failed
    if (badf) printf "; %d figures outside their tolerance", badf
    if (nofig) printf "; cases without figures:%s", nofig_list
    if (bad_exit != "") printf "; non-zero exit:%s", bad_exit
    if (bad_san != "") printf "; sanitizer reports:%s", bad_san
    printf ".\n"
    exit 1
  }
' "$RECORDS" >"$REPORT"
status=$?
cat "$REPORT"
echo
echo "(report: $REPORT, logs: $LOG_DIR)"
exit $status
