"""`denoiser infer`: a model over a dataset folder's sequences, one EXR per output frame; exit 2 for bad input."""

from __future__ import annotations

import pytest

from cli.main import main
from model.io.exr import open_exr, part_planes
from tests.builders import write_tiny_dataset


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("infer") / "data")


def test_a_split_runs_frame_by_frame_into_one_folder_per_sequence(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["infer", "--data", str(data), "--model", "accumulation", "--split", "train", "--scale", "2",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr()
    assert f"wrote 11 frames of 2 sequences to {out}" in printed.out and "beta: frame 5/5" in printed.err
    assert sorted(p.name for p in out.iterdir()) == ["alpha", "beta"]
    assert len(list((out / "alpha").glob("frame_*.exr"))) == 6
    with open_exr(out / "beta" / "frame_0004.exr") as exr:
        planes = part_planes(exr.parts[0])
        assert exr.parts[0].header["frame_index"] == 4 and exr.parts[0].header["sequence"] == "beta"
    assert sorted(planes) == ["B", "G", "R"] and planes["R"].shape == (32, 32)  # the output resolution at 2x


def test_named_sequences_and_bad_input(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["infer", "--data", str(data), "--model", "identity", "--sequences", "gamma", "--quiet",
                 "--out", str(out)]) == 0
    assert [p.name for p in out.iterdir()] == ["gamma"] and capsys.readouterr().err == ""
    assert main(["infer", "--data", str(data), "--model", "identity", "--sequences", "zeta", "--out", str(out)]) == 2
    assert "no sequence(s) 'zeta'" in capsys.readouterr().err
    assert main(["infer", "--data", str(data), "--model", "nope", "--out", str(out)]) == 2
    assert "unknown method 'nope'" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["infer", "--data", str(data), "--model", "identity", "--split", "test", "--sequences", "gamma",
              "--out", str(out)])
    assert exit_info.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
