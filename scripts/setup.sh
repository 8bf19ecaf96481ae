#!/usr/bin/env bash
# Installs what microray needs, only what is missing:
#  1. the Debian 12 packages (as root; elsewhere it says what to run), plus
#     Debian's nodejs and npm when `node` or `npm` is not on the PATH;
#  2. the schema test tools (ajv-cli, a JSON Schema 2020-12 validator;
#     js-yaml; Redocly's OpenAPI linter, @redocly/openapi-core) into
#     tests/schema/node_modules with `npm ci`, pinned by the committed
#     tests/schema/package-lock.json. Skipped when the installed tree was
#     made from the same lock file (a copy of it is kept in node_modules).
# Runs as root on a fresh machine (CI, containers).
#
#   scripts/setup.sh           everything: build, test, bench and fuzz tools
#   scripts/setup.sh --build   only what `make` needs to build microrayd and
#                              microray (the container image, docker/)
set -euo pipefail
ROOT=$(cd "$(dirname "$0")/.." && pwd)
BUILD_ONLY=0
case "${1:-}" in
  --build) BUILD_ONLY=1 ;;
  "") ;;
  *) echo "usage: $0 [--build]" >&2; exit 2 ;;
esac

BUILD_PACKAGES=(
  build-essential pkg-config
  libembree-dev          # Embree 3 ray tracing kernels
  libopenexr-dev openexr # OpenEXR 3 C API, and exrheader used by the tests
  libdeflate-dev         # zip_level 6-9 of the EXR writer, and the Adler-32 of its own deflate
  libassimp-dev          # asset import
  libcjson-dev libsqlite3-dev libmicrohttpd-dev libcurl4-openssl-dev
  libmeshoptimizer-dev
  libpng-dev             # PNG previews and contact sheets (core/render/preview.c), PNG height maps
  libjpeg-dev            # JPEG height maps and exemplars (core/asset/image.c)
)
TEST_PACKAGES=(
  assimp-testmodels      # the real models the examples and tests use
  libcmocka-dev
  openssl                # self-signed certificates for the TLS test (test_http_auth)
  curl                   # the README's curl examples, run as written by test_api
  groff-base             # test_cli: the manual pages pass groff's warnings
  systemd                # test_cli: systemd-analyze verify of the installed microrayd.service
  wrk                    # HTTP load generator for make bench (loopback only)
  gnuplot-nox            # make bench: the plots of bench/report.md (bench/report.sh)
  slurm-wlm munge        # a real single-node Slurm for the cluster test (test_slurm,
                         # scripts/slurm-local.sh; microray cluster, docs/scale.md)
  clang libclang-rt-14-dev  # the libFuzzer harnesses (make fuzz-build): clang 14 and its
                            # fuzzer/ASan/UBSan runtimes (only recommended by clang-14)
)

PACKAGES=("${BUILD_PACKAGES[@]}")
[ "$BUILD_ONLY" -eq 1 ] || PACKAGES+=("${TEST_PACKAGES[@]}")

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
# By command, not by package: a machine may have node and npm from elsewhere.
if [ "$BUILD_ONLY" -eq 0 ]; then
  command -v node >/dev/null 2>&1 || missing+=(nodejs)
  command -v npm >/dev/null 2>&1 || missing+=(npm)
fi

if [ ${#missing[@]} -gt 0 ]; then
  echo "setup: installing ${missing[*]}" >&2
  if [ "$(id -u)" -ne 0 ]; then
    echo "setup: not root; run: sudo apt-get install -y ${missing[*]}" >&2
    exit 1
  fi
  export DEBIAN_FRONTEND=noninteractive
  apt-get update -qq
  apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
fi

[ "$BUILD_ONLY" -eq 0 ] || exit 0

# Schema test tools (tests/unit/test_schema). No root needed: a local folder.
TOOLS="$ROOT/tests/schema"
STAMP="$TOOLS/node_modules/.microray-package-lock.json"
if [ -x "$TOOLS/node_modules/.bin/ajv" ] && cmp -s "$TOOLS/package-lock.json" "$STAMP"; then
  exit 0
fi
echo "setup: installing the schema test tools (npm ci in tests/schema)" >&2
(cd "$TOOLS" && npm ci --no-audit --no-fund --ignore-scripts --loglevel=error >/dev/null)
"$TOOLS/node_modules/.bin/ajv" help >/dev/null
cp "$TOOLS/package-lock.json" "$STAMP"
