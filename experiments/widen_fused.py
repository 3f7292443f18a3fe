"""Widen a trained fused model's network, computing the same function, for a fine-tune to start from
(model/methods/fused_growth.py): its layers get more channels, which read and write nothing until trained.

    .venv/bin/python experiments/widen_fused.py pretrained/fused-fast-x1/model.pt --width 24 --out runs/fast-w24.pt
    .venv/bin/denoiser train --method fused:fast --init-from runs/fast-w24.pt ...

The source is a checkpoint (`denoiser train`'s best.pt or a shipped model.pt); the widened file keeps its method,
preset, scale and run-time settings (the recurrence, the kernel limit, the running mean's window).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.training.checkpoint import load_checkpoint, save_checkpoint  # noqa: E402
from model.methods.fused_growth import widened_state_dict  # noqa: E402
from model.methods.registry import build_method  # noqa: E402


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", help="a fused model's checkpoint (best.pt, last.pt or a shipped model.pt)")
    parser.add_argument("--width", type=int, required=True, help="channels at the network's top level (shipped: 16)")
    parser.add_argument("--out", required=True, help="where to write the widened checkpoint")
    parser.add_argument("--seed", type=int, default=0, help="seed of the new channels' random weights")
    args = parser.parse_args()
    try:
        content = load_checkpoint(args.checkpoint)
        source = content["method"]
        if source["method"] != "fused":
            raise ValueError(f"{args.checkpoint} holds {source['method']}, not a fused model")
        method = build_method(f"fused:{source['preset']}", source["scale"])
        method.load_state_dict(widened_state_dict(content["model"], args.width, seed=args.seed))
    except (FileNotFoundError, ValueError, KeyError) as error:
        print(f"widen_fused: {error}", file=sys.stderr)
        return 2
    save_checkpoint(args.out, method=method, extra={"widened_from": str(args.checkpoint)})
    print(f"{args.out}: fused:{source['preset']} at {source['scale']}x, width {method.net.width}, "
          f"{sum(p.numel() for p in method.parameters())} parameters")
    return 0


if __name__ == "__main__":
    sys.exit(main())
