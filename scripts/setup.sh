#!/usr/bin/env bash
# Installs the Debian 12 packages microray needs, only those missing.
# Runs as root on a fresh machine (CI, containers); elsewhere it says what to run.
set -euo pipefail

PACKAGES=(
  build-essential pkg-config
  libembree-dev          # Embree 3 ray tracing kernels
  libopenexr-dev openexr # OpenEXR 3 C API, and exrheader used by the tests
  libassimp-dev assimp-testmodels  # asset import, and the real models examples/tests use
  libcjson-dev libsqlite3-dev libmicrohttpd-dev libcurl4-openssl-dev
  libmeshoptimizer-dev
  libcmocka-dev
  wrk                    # HTTP load generator for make bench (loopback only)
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done
[ ${#missing[@]} -eq 0 ] && exit 0

echo "setup: installing ${missing[*]}" >&2
if [ "$(id -u)" -ne 0 ]; then
  echo "setup: not root; run: sudo apt-get install -y ${missing[*]}" >&2
  exit 1
fi
export DEBIAN_FRONTEND=noninteractive
apt-get update -qq
apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
