#!/usr/bin/env bash
# make run: starts a local microrayd on 127.0.0.1 (default data directory,
# a free port), submits examples/skinned-walk.json with the microray client,
# which shows a progress bar and downloads the frames and stats into
# out/skinned-walk/, then stops the daemon.
set -euo pipefail
BUILD=${1:-build}
cd "$(dirname "$0")/.."
OUT=out/skinned-walk
PORT_FILE=$(mktemp)
trap 'rm -f "$PORT_FILE"' EXIT

"$BUILD"/microrayd serve --listen 127.0.0.1:0 --asset-root /usr/share/assimp/models \
  --port-file "$PORT_FILE" --quiet &
DAEMON=$!
stop_daemon() { kill -TERM "$DAEMON" 2>/dev/null || true; wait "$DAEMON" 2>/dev/null || true; }
trap 'stop_daemon; rm -f "$PORT_FILE"' EXIT

for _ in $(seq 100); do
  [ -s "$PORT_FILE" ] && break
  kill -0 "$DAEMON" 2>/dev/null || { echo "run: microrayd did not start" >&2; exit 1; }
  sleep 0.1
done
[ -s "$PORT_FILE" ] || { echo "run: microrayd did not start" >&2; exit 1; }
SERVER="http://127.0.0.1:$(cat "$PORT_FILE")"
echo "run: microrayd on $SERVER"
"$BUILD"/microray --server "$SERVER" submit examples/skinned-walk.json --wait --out "$OUT"
echo "run: frames in $OUT/0000.exr .. and statistics in $OUT/stats.json"
