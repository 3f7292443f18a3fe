"""Build a dataset of links to other datasets' sequences (no frames copied), each listed COPIES times, so a
training run reads them all in the proportions given.

    .venv/bin/python scripts/link_datasets.py data/reuse-mixed reuse:1:train,validation blender-train:4:train

Each SOURCE:COPIES:SPLITS names a dataset beside OUT, how many times each of its sequences is listed (listed once:
under its own name; more often: NAME_c0, NAME_c1, ...) and which of its splits are taken (each sequence keeps its
split). Running it again adds what is missing and keeps what is there.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from model.io.dataset import MANIFEST, Dataset  # noqa: E402
from model.names import SPLITS  # noqa: E402


def parse_source(text: str) -> tuple[str, int, tuple[str, ...]]:
    parts = text.split(":")
    if len(parts) != 3 or not parts[1].isdigit() or int(parts[1]) < 1:
        raise argparse.ArgumentTypeError(f"{text!r}: expected SOURCE:COPIES:SPLITS, e.g. reuse:1:train,validation")
    splits = tuple(parts[2].split(","))
    unknown = [split for split in splits if split not in SPLITS]
    if unknown:
        raise argparse.ArgumentTypeError(f"{text!r}: unknown split {unknown[0]!r} (splits: {', '.join(SPLITS)})")
    return parts[0], int(parts[1]), splits


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("out", type=Path, help="the dataset of links (created if missing), a folder beside the sources")
    parser.add_argument("sources", type=parse_source, nargs="+", metavar="SOURCE:COPIES:SPLITS")
    args = parser.parse_args()
    root: Path = args.out
    for source, _, _ in args.sources:
        if not (root.parent / source / MANIFEST).is_file():
            print(f"error: {root.parent / source} is not a dataset (no {MANIFEST})", file=sys.stderr)
            return 2
    linked = Dataset(root) if (root / MANIFEST).is_file() else Dataset.create(root)
    for source, copies, splits in args.sources:
        dataset = Dataset(root.parent / source)
        for split in splits:
            for name in dataset.names(split):
                for copy in range(copies):
                    link = root / (name if copies == 1 else f"{name}_c{copy}")
                    if not link.exists():
                        link.symlink_to(Path("..", source, name))
                    linked.add_sequence_dir(link.name, split, replace=True)
    print(f"{root}: {len(linked.names())} sequences")
    return 0


if __name__ == "__main__":
    sys.exit(main())
