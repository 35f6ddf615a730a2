#!/usr/bin/env bash
# Headless Chromium (Debian's) on a local page, with a profile of its own and the flags this
# machine needs (as root: no sandbox; on a closed network: no background connections):
#   headless.sh [chromium's arguments...] PAGE
# e.g. `--dump-dom PAGE` (the DOM once its scripts ran), or
# `--window-size=1240,2200 --screenshot=OUT.png PAGE`.
set -euo pipefail
[ $# -ge 1 ] || { echo "usage: headless.sh [chromium arguments...] PAGE" >&2; exit 2; }
page=$(realpath "${!#}")
profile=$(mktemp -d)
trap 'rm -rf "$profile"' EXIT
chromium --headless --no-sandbox --disable-gpu --disable-quic --no-first-run \
  --disable-background-networking --disable-component-update --disable-sync --hide-scrollbars \
  --user-data-dir="$profile" "${@:1:$#-1}" "file://$page"
