#!/usr/bin/env bash
# ICP on the adjacent ring pairs of the Stanford bunny scans, side by side with Open3D
# (../shared/bench/peer_icp.py) from the same initial guess: the truth moved 8° and 10 mm.
# Usage: bash bench/icp_bunny.sh [extra spinscan register flags…]
# Needs ../shared (data, peer script) and ../.venv-peers (bash ../shared/bench/setup.sh).
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED=${SHARED:-../shared}
PY=${PY:-../.venv-peers/bin/python}
DATA=$SHARED/data/stanford-bunny-scans
BIN=target/release/spinscan
cargo build --release --quiet
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
pairs="bun045:bun000 bun090:bun045 bun180:bun090 bun270:bun180 bun315:bun270 bun000:bun315"
for p in $pairs; do
  s=${p%%:*}; t=${p##*:}
  # 1. The initial guess (Open3D's run here is only to write it).
  "$PY" "$SHARED/bench/peer_icp.py" --conf "$DATA/bun.conf" --source "$DATA/$s.ply" --target "$DATA/$t.ply" \
    --init-offset 8,0.01 --write-init "$work/init.json" --runs 1 --iters 1 >/dev/null
  # 2. spinscan, then Open3D timed and both scored against the .conf in one call.
  "$BIN" register "$DATA/$s.ply" "$DATA/$t.ply" --init "$work/init.json" --max-distance 0.005 --repeat 5 -o "$work/ours.json" "$@" >/dev/null
  ms=$("$PY" -c 'import json,sys; print(json.load(open(sys.argv[1]))["register_ms"])' "$work/ours.json")
  "$PY" "$SHARED/bench/peer_icp.py" --conf "$DATA/bun.conf" --source "$DATA/$s.ply" --target "$DATA/$t.ply" \
    --init-offset 8,0.01 --runs 5 --eval "$work/ours.json" --eval-ms "$ms" | sed "s|$work/ours.json|spinscan register|"
  echo
done
