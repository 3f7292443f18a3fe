"""Ship a trained checkpoint as a pretrained model of the repository (model/deployment/pretrained.py): the weights without
optimizer state under pretrained/NAME/model.pt and a manifest with the training recipe, the sha256 checked on every
load, and the held-out metrics copied from an evaluation report of the same run (else "pending").

    .venv/bin/python scripts/ship_pretrained.py runs/fused-balanced-x1/best.pt --name fused-balanced-x1 \
        --data data/reuse --dataset-script scripts/generate_reuse_data.sh \
        --training-script scripts/reproduce_reuse_results.sh --report var/results/reuse_x1.json

--after-shipped NAME: the checkpoint was fine-tuned from the shipped model NAME (--init-from pretrained/NAME/model.pt);
the stages recorded in its manifest, then that model itself, are recorded before any --stage. --remeasure: the
checkpoint is the shipped model NAME itself, evaluated again in the report's run; only its held-out section is
replaced. The run-time settings (fused: --history-before-kernel / --history-after-kernel, --kernel-max-pixels,
--mean-max-frames, --stale-test-sigmas, ...; WSKPN, AFN, JNDS and MUNet: --rectify-history / --no-rectify-history)
ship the checkpoint's weights running another setting:

    .venv/bin/python scripts/ship_pretrained.py pretrained/wskpn-s-x1/model.pt --name wskpn-s-x1 \
        --after-shipped wskpn-s-x1 --rectify-history

Every flag: below, and docs/pretrained.md, "Maintainers: shipping a model".
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.deployment.pretrained import (  # noqa: E402
    HISTORY_SETTINGS,
    PRETRAINED_DIR,
    RUN_TIME_SETTINGS,
    PretrainedError,
    UnknownPretrained,
    get_pretrained,
    remeasure_shipped,
    ship_checkpoint,
)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--name", required=True, help="the model's name, METHOD-PRESET-xSCALE by convention")
    parser.add_argument("--data", type=Path, default=None, help="the training dataset (its recipe is recorded)")
    parser.add_argument("--dataset-script", default=None, help="the script that renders that dataset")
    parser.add_argument("--training-script", default=None, help="the script that trained the checkpoint")
    parser.add_argument("--report", type=Path, default=None, help="denoiser evaluate --out JSON of the held-out split")
    parser.add_argument("--report-source", default=None, help="the checkpoint as the report's row names it")
    parser.add_argument("--stage", type=Path, action="append", default=None, metavar="CHECKPOINT",
                        help="an earlier training this checkpoint started from (--init-from); repeat, first to last")
    parser.add_argument("--after-shipped", default=None, metavar="NAME",
                        help="the shipped model the first stage (or the checkpoint) was fine-tuned from (--init-from "
                             "pretrained/NAME/model.pt): its recorded stages and itself are recorded first")
    recurrence = parser.add_mutually_exclusive_group()
    recurrence.add_argument("--history-before-kernel", dest="history_before_kernel", action="store_const",
                            const=True, default=None,
                            help="fused only: the blend before the kernel is the next frame's history")
    recurrence.add_argument("--history-after-kernel", dest="history_before_kernel", action="store_const",
                            const=False, help="fused only: the filtered output is the next frame's history")
    parser.add_argument("--kernel-max-pixels", type=int, default=None, metavar="N",
                        help="fused only: frames of more than N render pixels skip the output kernel (0: none do)")
    parser.add_argument("--mean-max-frames", type=int, default=None, metavar="N",
                        help="fused only: the running mean of OIDN's estimates averages at most N frames (then an "
                             "exponential average of that length)")
    parser.add_argument("--stale-test-sigmas", type=float, default=None, metavar="Z",
                        help="fused only: where the running mean's 9x9 window mean is more than Z standard errors "
                             "off the 1 spp frame's, the history's weight goes to OIDN's estimate (0: no test)")
    parser.add_argument("--stale-region-pixels", type=int, default=None, metavar="N",
                        help="fused only: the stale-history test also reads the root mean square of its z's over "
                             "N x N render pixels (odd; 0: no regional test), and the sample mean restarts on it")
    parser.add_argument("--sample-mean-frames", type=int, default=None, metavar="N",
                        help="fused only: OIDN reads a running mean of up to N 1 spp frames and their guides "
                             "(0: the single frame)")
    parser.add_argument("--sample-mean-trust-power", type=float, default=None, metavar="P",
                        help="fused only: the sample mean keeps the network's history share to the power P of its "
                             "frames (default 2)")
    parser.add_argument("--albedo-detail-frames", type=int, default=None, metavar="N",
                        help="fused at 2x only: the output takes the texture detail of the albedo gathered on the "
                             "target grid from up to N jittered frames (0: none)")
    unjitter = parser.add_mutually_exclusive_group()
    unjitter.add_argument("--unjitter-estimate", dest="unjitter_estimate", action="store_const", const=True,
                          default=None, help="fused only: at 1x OIDN's estimate is read at the pixel centres from "
                                             "its samples' jittered positions (always so at 2x)")
    unjitter.add_argument("--no-unjitter-estimate", dest="unjitter_estimate", action="store_const", const=False,
                          help="fused at 1x only: OIDN's estimate is used where its samples lie")
    rectify = parser.add_mutually_exclusive_group()
    rectify.add_argument("--rectify-history", dest="rectify_history", action="store_const", const=True, default=None,
                         help="the seed methods: clip the reprojected history to the current frame first")
    rectify.add_argument("--no-rectify-history", dest="rectify_history", action="store_const", const=False,
                         help="the seed methods: use the reprojected history as it is")
    parser.add_argument("--remeasure", action="store_true",
                        help="CHECKPOINT is the shipped NAME: replace only its held-out section from --report")
    parser.add_argument("--root", type=Path, default=PRETRAINED_DIR, help="folder of pretrained models")
    args = parser.parse_args()
    settings = {name: getattr(args, name) for name in [*RUN_TIME_SETTINGS, *HISTORY_SETTINGS]
                if getattr(args, name) is not None}
    if args.remeasure and (args.report is None or args.stage or args.after_shipped or args.data or settings):
        parser.error("--remeasure takes --report (and --report-source), and no --stage, --after-shipped, --data, "
                     "--history-*-kernel or other run-time setting")
    report = None
    if args.report is not None:
        if not args.report.is_file():
            print(f"--report {args.report} does not exist", file=sys.stderr)
            return 2
        report = json.loads(args.report.read_text())
    try:
        if args.remeasure:
            return _remeasure(args, report)
        model = ship_checkpoint(args.checkpoint, args.name, root=args.root, dataset_dir=args.data,
                                dataset_script=args.dataset_script, training_script=args.training_script,
                                report=report, report_source=args.report_source,
                                report_path=None if args.report is None else str(args.report), stages=args.stage,
                                after_shipped=args.after_shipped, **settings)
    except (PretrainedError, UnknownPretrained, FileNotFoundError, ValueError) as error:
        print(f"error: {error}", file=sys.stderr)
        return 2
    print(f"shipped {model.name}: {model.path} ({model.manifest['bytes']} bytes, sha256 {model.sha256[:12]}..., "
          f"step {model.manifest['training']['step']}, held-out: {model.held_out['status']})")
    return 0


def _remeasure(args: argparse.Namespace, report: dict) -> int:
    shipped = get_pretrained(args.name, args.root)
    if args.checkpoint.resolve() != shipped.path.resolve():
        print(f"--remeasure: {args.checkpoint} is not the shipped {args.name} ({shipped.path})", file=sys.stderr)
        return 2
    model = remeasure_shipped(args.name, report, args.report_source or str(args.checkpoint), str(args.report),
                              args.root)
    print(f"remeasured {model.name}: held-out PSNR {model.held_out_row()['psnr']} in {args.report}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
