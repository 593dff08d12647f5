#!/bin/sh
# The one command behind docs/foxglove-studio-demo.png: a 30 s demo run, its log opened in
# Foxglove Studio 1.48 (built from @foxglove/studio-base) with config/foxglove/glider-1.json,
# in headless chromium, screenshot at the end of the run.
#
#   tools/foxglove_studio/shoot.sh [OUT.png]      (default docs/foxglove-studio-demo.png)
#
# Needs: the project's .venv (make build), node 20 with npm, /usr/bin/chromium
# (apt-get install -y chromium). Network: the npm registry once (npm ci), then 127.0.0.1 only.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
out=$(realpath -m "${1:-$root/docs/foxglove-studio-demo.png}")
[ -x /usr/bin/chromium ] || { echo "shoot.sh: /usr/bin/chromium missing (apt-get install -y chromium)" >&2; exit 1; }
[ -x "$root/.venv/bin/glider-hil" ] || { echo "shoot.sh: $root/.venv missing (make build)" >&2; exit 1; }

cd "$here"
[ -d node_modules/@foxglove/studio-base/assets ] || npm ci --no-audit --no-fund
node build.mjs

tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$root/.venv/bin/glider-hil" demo --duration 30 --log-dir "$tmp/logs"
log=$(ls "$tmp"/logs/*.mcap | head -n 1)
end=$("$root/.venv/bin/python" compat_log.py "$log" -o "$tmp/studio.mcap" | sed -n 's/^end //p')
node screenshot.mjs --log "$tmp/studio.mcap" --out "$out" --time "$end" --width 1600 --height 1200
