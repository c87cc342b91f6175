#!/usr/bin/env bash
# Checks systemd/spinscand.service with `systemd-analyze verify`, with ExecStart pointed at
# the built binary. Fails on any message it prints (it only warns on unknown keys).
set -euo pipefail
cd "$(dirname "$0")/.."
bin="${1:-$PWD/target/debug/spinscand}"
if ! command -v systemd-analyze >/dev/null 2>&1; then
  echo "systemd/verify.sh: systemd-analyze is missing (apt-get install systemd)" >&2
  exit 1
fi
if [ ! -x "$bin" ]; then
  echo "systemd/verify.sh: $bin is not built (cargo build --bin spinscand)" >&2
  exit 1
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
sed "s|^ExecStart=/usr/local/bin/spinscand|ExecStart=$bin|" systemd/spinscand.service > "$tmp/spinscand.service"
out="$(systemd-analyze verify "$tmp/spinscand.service" 2>&1)" || { echo "$out" >&2; exit 1; }
if [ -n "$out" ]; then
  echo "systemd-analyze verify printed (any message fails the check):" >&2
  echo "$out" >&2
  exit 1
fi
echo "systemd/spinscand.service: systemd-analyze verify clean"
