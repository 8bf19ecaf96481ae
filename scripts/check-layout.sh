#!/usr/bin/env bash
# The architecture's rules that a grep can check (../shared/ARCHITECTURE.md):
#  - nothing outside a kind's folder names a kind: no kind's name (or its
#    mr_<kind>_ identifiers, or its folder) in server/, core/render/,
#    core/job.[ch] or core/kinds/*.[ch]; only core/kinds/registry.c lists them;
#  - core does not include server headers (it is compiled without -Iserver);
#  - server/ and bench/ include from core only microray.h, the public API
#    (tests/ may include internals; the benchmarks not even through the
#    tests' support headers).
# Prints each violation and exits 1 if there is any. Run by make test/check.
set -uo pipefail
cd "$(dirname "$0")/.."
status=0
kinds=$(find core/kinds -mindepth 1 -maxdepth 1 -type d -printf '%f\n' | sort)
generic=(server core/render core/job.h core/job.c)
for f in core/kinds/*.c core/kinds/*.h; do
  [ "$f" = core/kinds/registry.c ] || generic+=("$f")
done
for k in $kinds; do
  # "mesh" is also a plain word (assets hold meshes): its identifiers only
  pattern="$k|mr_${k}_[a-z0-9_]*|mr_kind_$k|kinds/$k/"
  [ "$k" = mesh ] && pattern="mr_kind_$k|kinds/$k/"
  hits=$(grep -rniwE "$pattern" "${generic[@]}" 2>/dev/null || true)
  if [ -n "$hits" ]; then
    echo "check-layout: the kind '$k' is named outside core/kinds/$k/ and the registry:"
    echo "$hits" | sed 's/^/  /'
    status=1
  fi
done
hits=$(grep -rnE '#include "(daemon|http|store|worker|job_json|render_cmd|files|cache|stats_json|schema_gen)\.h"' core || true)
if [ -n "$hits" ]; then
  echo "check-layout: core includes server headers:"
  echo "$hits" | sed 's/^/  /'
  status=1
fi
# A quoted include names a core header when core/<name> exists (and the
# including file's own directory has no such file).
core_includes() { # files...
  for f in "$@"; do
    grep -nE '^[[:space:]]*#[[:space:]]*include[[:space:]]*"[^"]+"' "$f" 2>/dev/null |
      while IFS= read -r line; do
        inc=$(printf '%s\n' "$line" | sed -E 's/.*#[[:space:]]*include[[:space:]]*"([^"]+)".*/\1/')
        [ "$inc" = microray.h ] && continue
        [ -e "core/$inc" ] && [ ! -e "$(dirname "$f")/$inc" ] && echo "$f:$line"
      done
  done
}
hits=$(core_includes server/*.c server/*.h)
if [ -n "$hits" ]; then
  echo "check-layout: server includes core headers other than microray.h:"
  echo "$hits" | sed 's/^/  /'
  status=1
fi
hits=$(core_includes bench/*.c bench/*.h
       grep -nE '^[[:space:]]*#[[:space:]]*include[[:space:]]*"[^"]*tests/' bench/*.c bench/*.h 2>/dev/null)
if [ -n "$hits" ]; then
  echo "check-layout: benchmarks include core headers other than microray.h:"
  echo "$hits" | sed 's/^/  /'
  status=1
fi
[ $status -eq 0 ] && echo "check-layout: ok (kinds: $(echo $kinds | tr '\n' ' '))"
exit $status
