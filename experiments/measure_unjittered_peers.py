"""Evaluate the OIDN and OIDN + TAA peers with OIDN's estimate read back at the pixel centres, as the 1x fused models
do (``unjitter_estimate``): what the peers would score if they did the same. The peers as every table shows them
use the estimate where its samples lie; this measures how much of the fused models' lead the read alone is worth
(findings: docs/results/findings.md).

    .venv/bin/python experiments/measure_unjittered_peers.py --data data/reuse --split test \
        --out var/results/reuse_x1_unjittered_peers.json

Writes a ``denoiser evaluate`` report (1x, no timing: the read costs the same for every quality) whose rows are
``oidn:Q`` and ``oidn-taa:Q`` with the read; FovVideoVDP unless --no-vdp.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import model.methods.oidn as oidn  # noqa: E402
import model.methods.oidn_taa as oidn_taa  # noqa: E402
from model.evaluation.evaluate import evaluate, format_table  # noqa: E402
from model.methods.fused import unjittered_resample  # noqa: E402
from model.methods.oidn_taa import reinhard, reinhard_inverse  # noqa: E402

PEERS = [f"{name}:{quality}" for name in ("oidn", "oidn-taa") for quality in oidn.QUALITIES]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--split", default="test")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--no-vdp", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    denoise = oidn.oidn_denoise

    def at_pixel_centres(frame, quality):
        # the fused models' read: tone-mapped, bicubic at the frame's jitter, clamped to the 3x3 neighbours
        return reinhard_inverse(unjittered_resample(reinhard(denoise(frame, quality)), frame.jitter, 1))

    # Both peers look OIDN up in their own module at each call, so the read replaces it for them alone.
    oidn.oidn_denoise = oidn_taa.oidn_denoise = at_pixel_centres
    try:
        report = evaluate(args.data, PEERS, args.split, 1, threads=args.threads, vdp=not args.no_vdp,
                          timing_reference=None)
    except (ValueError, FileNotFoundError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    report["note"] = "OIDN's estimate read back at the pixel centres (experiments/measure_unjittered_peers.py)"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(format_table(report))
    return 0


if __name__ == "__main__":
    sys.exit(main())
