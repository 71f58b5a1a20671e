#!/usr/bin/env bash
# Set up (or reuse) .venv and run the main job on the built-in synthetic scenes:
# the quick transfer experiment (meta-train on scene A, transfer to scene B vs scratch,
# 3 seeds), then a flight of the transferred policy through the MAVLink emulator.
# Writes runs/quick/ (report.md, curves, trajectories, flight/); rerun to resume.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
exec .venv/bin/geonav experiment run configs/quick.toml --jobs 2 "$@"
