#!/usr/bin/env bash
# make run: starts a fresh local microrayd on 127.0.0.1 (a free port) with a
# data directory of its own under $TMPDIR, submits examples/skinned-walk.json
# with the microray client, which shows a progress bar and downloads the
# frames and stats into out/skinned-walk/, then stops the daemon and removes
# its data directory - also when interrupted (Ctrl-C), so nothing is left
# in ~/.local/share/microray and the next run starts from nothing.
#
#   scripts/run-example.sh [BUILD]
#   MICRORAY_RUN_JOB=JOB.json MICRORAY_RUN_OUT=DIR scripts/run-example.sh   (another job, another folder)
set -euo pipefail
BUILD=${1:-build}
cd "$(dirname "$0")/.."
JOB=${MICRORAY_RUN_JOB:-examples/skinned-walk.json}
OUT=${MICRORAY_RUN_OUT:-out/$(basename "$JOB" .json)}
DATA=$(mktemp -d "${TMPDIR:-/tmp}/microray-run.XXXXXX")
PORT_FILE=$DATA/port
DAEMON=

cleanup() {
  if [ -n "$DAEMON" ]; then
    kill -TERM "$DAEMON" 2>/dev/null || true
    wait "$DAEMON" 2>/dev/null || true
  fi
  rm -rf "$DATA"
}
trap cleanup EXIT
# Ctrl-C or a kill: stop (the EXIT trap cleans up) with the shell's usual status
trap 'exit 130' INT
trap 'exit 143' TERM

"$BUILD"/microrayd serve --listen 127.0.0.1:0 --data "$DATA/data" \
  --asset-root /usr/share/assimp/models --port-file "$PORT_FILE" --quiet &
DAEMON=$!

for _ in $(seq 100); do
  [ -s "$PORT_FILE" ] && break
  kill -0 "$DAEMON" 2>/dev/null || { echo "run: microrayd did not start" >&2; exit 1; }
  sleep 0.1
done
[ -s "$PORT_FILE" ] || { echo "run: microrayd did not start" >&2; exit 1; }
SERVER="http://127.0.0.1:$(cat "$PORT_FILE")"
echo "run: microrayd (pid $DAEMON) on $SERVER, data in $DATA (removed at the end)"
# Ctrl-C reaches the client (it says how to resume) and this script, whose
# trap then stops the daemon; the daemon, started in the background, ignores
# the terminal's SIGINT and is stopped by the trap alone
"$BUILD"/microray --server "$SERVER" submit "$JOB" --wait --out "$OUT"
echo "run: frames in $OUT/0000.exr .. and statistics in $OUT/stats.json"
