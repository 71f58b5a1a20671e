#!/usr/bin/env bash
# Set up (or reuse) .venv and run the main job on the built-in synthetic scenes.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/geonav demo --out out/demo "$@"
