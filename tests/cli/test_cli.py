"""The `denoiser` command line: documented options, real runs, clear errors with exit status 2."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from model.io.dataset import Dataset
from model.io.exr import read_frame
from cli.main import build_parser, main
from tests.model.data.conftest import requires_llvm


def test_generate_help_documents_every_option(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["generate", "--help"])
    assert exit_info.value.code == 0
    text = capsys.readouterr().out
    generate = next(a for a in build_parser()._subparsers._group_actions[0].choices.items() if a[0] == "generate")[1]
    for action in generate._actions:
        for flag in action.option_strings:
            assert flag in text
        if action.option_strings and action.help:
            assert action.help.split()[0] in text
    for option in ("--scene", "--frames", "--size", "--ref-spp", "--seed", "--out", "--split", "--scales"):
        assert option in text


@requires_llvm
def test_generate_writes_a_dataset_and_refuses_to_overwrite(tmp_path, capsys):
    out = tmp_path / "data"
    args = ["generate", "--scene", "glass", "--frames", "2", "--size", "24x16", "--ref-spp", "4", "--albedo-spp", "2",
            "--seed", "7", "--out", str(out), "--split", "test", "--quiet"]
    assert main(args) == 0
    printed = capsys.readouterr().out
    assert "test" in printed and "glass" in printed
    dataset = Dataset(out)
    assert dataset.names("test") == ["glass_s7"]
    frame = read_frame(out / "glass_s7" / "frame_0001.exr")
    assert frame.resolution == (24, 16) and frame.scales == (1, 2) and frame.sequence == "glass_s7"
    assert sorted(frame.reference_albedos) == sorted(frame.reference_specular_albedos) == [1, 2]
    before = (out / "glass_s7" / "frame_0001.exr").read_bytes()

    assert main(args) == 2
    assert "exists" in capsys.readouterr().err
    assert (out / "glass_s7" / "frame_0001.exr").read_bytes() == before
    assert main(args + ["--overwrite"]) == 0  # deterministic: the same bytes come back
    np.testing.assert_array_equal(read_frame(out / "glass_s7" / "frame_0001.exr").color, frame.color)


@pytest.mark.parametrize("argv, message", [
    (["generate", "--scene", "nope", "--out", "x"], "unknown scene 'nope'"),
    (["summary", "/nonexistent/dataset"], "/nonexistent/dataset"),
    (["preview", "/nonexistent/frame.exr", "--out", "x.png"], "/nonexistent/frame.exr"),
    (["generate", "--scene", "glass", "--out", "/nonexistent/cuda-data", "--variant", "cuda_ad_rgb"]
     if not torch.cuda.is_available() else ["generate", "--scene", "moon", "--out", "x"],
     "needs a CUDA GPU" if not torch.cuda.is_available() else "unknown scene 'moon'"),
])
def test_bad_input_exits_2_with_a_message_naming_it(argv, message, capsys):
    assert main(argv) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv", [
    ["generate", "--scene", "glass", "--out", "x", "--frames", "0"],
    ["generate", "--scene", "glass", "--out", "x", "--size", "12y5"],
    ["generate", "--scene", "glass", "--out", "x", "--scales", "3"],
])
def test_invalid_option_values_are_usage_errors(argv, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert "error" in capsys.readouterr().err


def test_scenes_lists_every_recipe(capsys):
    from model.data.scenes import SCENES

    assert main(["scenes"]) == 0
    printed = capsys.readouterr().out
    assert all(name in printed for name in SCENES)


@requires_llvm
def test_preview_writes_a_png(tmp_path):
    out = tmp_path / "data"
    main(["generate", "--scene", "metals", "--frames", "1", "--size", "16", "--ref-spp", "2", "--out", str(out),
          "--quiet"])
    png = tmp_path / "sheet.png"
    assert main(["preview", str(out / "metals_s0"), "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert main(["preview", str(out / "metals_s0"), "--index", "5", "--out", str(png)]) == 2


def test_preview_of_output_exrs_writes_the_image_display_encoded(tmp_path, capsys):
    """The plain R/G/B EXRs the service, stream and infer write: the PNG is the image, clip(x, 0, 1) ** (1/2.2)."""
    import matplotlib.image

    from model.io.exr import write_image

    folder = tmp_path / "out" / "seq"
    folder.mkdir(parents=True)
    for index, value in enumerate((0.0, 0.25)):
        image = np.full((6, 10, 3), value, dtype=np.float32)
        image[0, 0] = (4.0, -1.0, 1.0)  # HDR and negative values clip
        write_image(folder / f"frame_{index:04d}.exr", image, {"frame_index": index, "sequence": "seq"})
    png = tmp_path / "last.png"
    assert main(["preview", str(folder), "--index", "-1", "--out", str(png)]) == 0
    assert "frame_0001.exr" in capsys.readouterr().out
    pixels = matplotlib.image.imread(png)[..., :3]
    assert pixels.shape == (6, 10, 3)
    np.testing.assert_allclose(pixels[3, 5], 0.25 ** (1 / 2.2), atol=1 / 255)  # 136/255, not 64/255 (linear)
    np.testing.assert_allclose(pixels[0, 0], (1.0, 0.0, 1.0), atol=1 / 255)
    assert main(["preview", str(folder / "frame_0000.exr"), "--out", str(png)]) == 0
    assert matplotlib.image.imread(png)[3, 5, 0] == 0.0
    assert main(["preview", str(folder), "--index", "2", "--out", str(png)]) == 2
    assert "out of range (0..1" in capsys.readouterr().err
    (tmp_path / "empty").mkdir()
    assert main(["preview", str(tmp_path / "empty"), "--out", str(png)]) == 2
    assert "neither a sequence folder" in capsys.readouterr().err


def test_preview_of_a_frame_bundle_file_draws_its_buffers_not_an_image(tmp_path, capsys):
    import matplotlib.image

    from model.io.exr import is_image_exr, write_frame
    from tests.builders import gradient_frame

    path = tmp_path / "frame_0000.exr"
    write_frame(path, gradient_frame(0, 0, (1,)))
    assert not is_image_exr(path)
    png = tmp_path / "sheet.png"
    assert main(["preview", str(path), "--out", str(png)]) == 0
    assert "output image" not in capsys.readouterr().out
    assert matplotlib.image.imread(png).shape[1] > 16 * 4  # a sheet of panels, not the 16x16 frame


def test_the_settings_reach_the_native_kernels_and_bad_ones_are_refused(monkeypatch, tmp_path, capsys):
    from core.settings import get_settings
    from model.ops import native

    monkeypatch.setenv("DENOISER_NATIVE_KERNELS", "false")
    monkeypatch.setenv("DENOISER_NATIVE_CACHE_DIR", str(tmp_path / "kernels"))
    try:
        assert main(["scenes"]) == 0
        assert not native.enabled() and native._cache_dir() == tmp_path / "kernels"
        monkeypatch.setenv("DENOISER_NATIVE_KERNELS", "sometimes")
        get_settings.cache_clear()
        assert main(["scenes"]) == 2
        assert "native_kernels" in capsys.readouterr().err
    finally:
        get_settings.cache_clear()
        native.configure(True, None)
