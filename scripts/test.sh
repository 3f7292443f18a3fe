#!/usr/bin/env bash
# Runs the test suite: `scripts/test.sh` (default suite, under 15 minutes on 2 cores) or
# `scripts/test.sh --slow` (only the tests marked slow). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
marker="not slow"
if [ "${1:-}" = "--slow" ]; then marker="slow"; shift; fi
exec .venv/bin/python -m pytest -m "$marker" "$@"
