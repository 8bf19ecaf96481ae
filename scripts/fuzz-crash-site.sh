#!/usr/bin/env bash
# fuzz-crash-site.sh LOG REGEX: exits 0 if the failure logged in LOG (a
# libFuzzer run of a sanitized harness) happened inside a library whose
# module matches the extended regex REGEX, 1 otherwise (our code, or no
# REGEX). Used by scripts/run-fuzz.sh for tests/fuzz/<harness>.tolerate.
#
# Inside such a library means: a libFuzzer timeout or out-of-memory (the
# harnesses that tolerate a library cap its run time and memory), an assimp
# ai_assert abort, or a crash whose first stack frame that is not the
# runtime matches REGEX. The runtime is libc, the sanitizers, libFuzzer and
# the allocator entry points the sanitizer intercepts (free, malloc, ...):
# a library that corrupts the heap is caught when it next calls free, in a
# frame of our binary's ASan interceptor, and the frame below it names the
# caller (the library, or our code for our own bad free); so is one that
# corrupts ASan's own chunk headers, which ASan reports as a failed CHECK
# of its allocator (no "ERROR:" line) when it recycles its quarantine
# inside some later free. That caller need not be the one that did the
# damage (any free may recycle the quarantine): a heuristic, sound here
# because our code is instrumented, so its own bad write is reported with
# an "ERROR:" line where it happens. A leak report is always ours (we
# release what a library hands us).
# Tested by tests/fuzz/crash-site/run.sh on stored logs.
set -uo pipefail
log=${1:?usage: fuzz-crash-site.sh LOG REGEX}
lib=${2:-}
[ -n "$lib" ] || exit 1
grep -qE 'ERROR: libFuzzer: (timeout|out-of-memory)|ai_assert failure' "$log" && exit 0
awk -v lib="$lib" '
  /ERROR: (AddressSanitizer|UndefinedBehaviorSanitizer|libFuzzer)|AddressSanitizer: CHECK failed/ { on = 1; next }
  on && /^[[:space:]]*#[0-9]+ / {
    if ($0 ~ /libc\.so|sanitizer|fuzzer::|__interceptor|__asan|__ubsan|\/nptl\/|abort\.c|raise\.c|pthread_kill|libclang_rt/) next
    if ($0 ~ / in (free|malloc|calloc|realloc|reallocarray|posix_memalign|aligned_alloc|memalign|valloc|operator new|operator delete)([ (<]|\[\])/) next
    found = ($0 ~ lib); exit
  }
  END { exit found ? 0 : 1 }' "$log"
