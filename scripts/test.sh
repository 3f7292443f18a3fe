#!/usr/bin/env bash
# Runs the test suite: `scripts/test.sh` (default suite, a few minutes on 2 cores) or
# `scripts/test.sh --slow` (only the tests marked slow). Extra arguments go to pytest.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh
# The offline API docs test drives a real Chromium (Debian's package); where it cannot be installed, that one
# test is skipped with its reason and everything else still runs.
bash scripts/install.sh --browser > /dev/null || echo "[test] Chromium could not be installed: the /docs browser test will be skipped"
# The API replicas test runs the real reverse proxy (Debian's haproxy) the same way.
bash scripts/install.sh --proxy > /dev/null || echo "[test] HAProxy could not be installed: the API replicas test will be skipped"
marker="not slow"
if [ "${1:-}" = "--slow" ]; then marker="slow"; shift; fi
status=0
.venv/bin/python -m pytest -m "$marker" "$@" || status=$?
# pytest exits 5 when the selection is empty (no slow tests selected): that is not a failure.
if [ "$status" = 5 ]; then echo "no tests selected by -m '$marker'"; exit 0; fi
exit "$status"
