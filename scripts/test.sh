#!/usr/bin/env bash
# Set up (or reuse) .venv and run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/setup_env.sh
# two workers, each taking whole modules (module fixtures such as the Ray cluster stay in
# one process); GEONAV_TEST_WORKERS=0 runs in this process. --durations: the slowest tests.
exec .venv/bin/python -m pytest -q -n "${GEONAV_TEST_WORKERS:-2}" --dist loadfile \
  --durations=15 "$@"
