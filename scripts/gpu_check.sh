#!/usr/bin/env bash
# The GPU checks in one run (about 10 minutes on one H100/H200): every CUDA test of the suite, then the fused speed
# suite with --device cuda at 1080p and 1080p -> 4K (CUDA graphs against eager, OIDN on its CUDA device).
#   bash scripts/gpu_check.sh [RESULTS_DIR]   (default docs/results; the report is speed_<gpu name>.json/.md/.png)
# PYTHON names the interpreter (default .venv/bin/python, else python3); it needs torch with CUDA and pyoidn.
set -uo pipefail
cd "$(dirname "$0")/.."
results="${1:-docs/results}"
python="${PYTHON:-.venv/bin/python}"
[ -x "$python" ] || python=python3
if ! "$python" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 1)"; then
    echo "gpu_check: $python sees no CUDA device (torch.cuda.is_available() is False)" >&2
    exit 2
fi
"$python" -c "import torch; print('gpu_check:', torch.cuda.get_device_name(), 'torch', torch.__version__)"

# (a) every test that skips without CUDA (its skipif reason names CUDA or a GPU), from the test files that mention it
mapfile -t files < <(grep -rl --include='test_*.py' -i "cuda" tests)
"$python" - "${files[@]}" <<'PY'
import sys

import pytest


class CudaTestsOnly:
    def pytest_collection_modifyitems(self, config, items):
        def needs_cuda(item):
            return any(word in str(mark.kwargs.get("reason", "")).lower() for mark in item.iter_markers("skipif")
                       for word in ("cuda", "gpu"))
        keep = [item for item in items if needs_cuda(item)]
        config.hook.pytest_deselected(items=[item for item in items if not needs_cuda(item)])
        items[:] = keep


sys.exit(pytest.main(["-q", "-rs", "-p", "no:cacheprovider", *sys.argv[1:]], plugins=[CudaTestsOnly()]))
PY
tests_status=$?

# (b) the fused suite on the GPU: CUDA graphs timed against the eager step (the fp32 eager column) on the same frames
"$python" scripts/bench_resolution_scaling.py --suite fused --device cuda --threads 8 --frames 30 \
    --size 1920x1080 --size 3840x2160 --results "$results"
bench_status=$?
echo "gpu_check: CUDA tests exit $tests_status, benchmark exit $bench_status"
[ "$tests_status" = 0 ] && [ "$bench_status" = 0 ]
