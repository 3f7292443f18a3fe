"""scripts/link_datasets.py builds a dataset of links to other datasets' sequences, in given proportions."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from model.io.dataset import Dataset
from tests.builders import write_tiny_dataset

ROOT = Path(__file__).resolve().parents[1]


def link(*arguments: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "link_datasets.py"), *arguments],
                          capture_output=True, text=True)


def test_sequences_are_linked_with_their_splits_and_copies(tmp_path):
    first, second = write_tiny_dataset(tmp_path / "first"), write_tiny_dataset(tmp_path / "second")
    result = link(str(tmp_path / "mixed"), "first:1:train,validation", "second:3:train")
    assert result.returncode == 0, result.stderr
    mixed, a, b = Dataset(tmp_path / "mixed"), Dataset(first), Dataset(second)
    assert mixed.names("validation") == a.names("validation")
    expected = a.names("train") + [f"{name}_c{k}" for name in b.names("train") for k in range(3)]
    assert sorted(mixed.names("train")) == sorted(expected) and mixed.names("test") == []
    copy = tmp_path / "mixed" / f"{b.names('train')[0]}_c2"
    assert copy.is_symlink() and copy.resolve() == (second / b.names("train")[0]).resolve()
    again = link(str(tmp_path / "mixed"), "first:1:train,validation", "second:3:train")  # adds nothing twice
    assert again.returncode == 0 and sorted(Dataset(tmp_path / "mixed").names("train")) == sorted(expected)


def test_a_missing_source_or_a_bad_argument_is_refused_with_a_message(tmp_path):
    write_tiny_dataset(tmp_path / "first")
    missing = link(str(tmp_path / "mixed"), "first:1:train", "nowhere:1:train")
    assert missing.returncode == 2 and "nowhere is not a dataset" in missing.stderr
    assert not (tmp_path / "mixed").exists()  # nothing built from half the sources
    for bad, message in (("first:0:train", "SOURCE:COPIES:SPLITS"), ("first:1:training", "unknown split")):
        result = link(str(tmp_path / "mixed"), bad)
        assert result.returncode == 2 and message in result.stderr
