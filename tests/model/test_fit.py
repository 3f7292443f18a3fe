"""model.fit: the ladder's choice for every target kind with fake measurements (known answers), early stops,
progress and tracking, target parsing, and reuse of trained presets (tiny method, tiny data, a fake registry)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

from model.fit.choice import (
    REUSED_CHECKPOINT,
    REUSED_REGISTRY,
    SKIPPED,
    TRAINED,
    Candidate,
    Measurement,
    Obtained,
    run_ladder,
)
from model.fit.plan import FitConfig, plan_fit
from model.fit.report import format_ladder
from model.fit.runner import fit
from model.fit.target import Target
from tests.builders import write_tiny_dataset
from tests.model.training_fixtures import TINY_METHOD

# A four-preset family, given out of order: the ladder sorts by FLOPs per pixel.
CANDIDATES = [Candidate("l", 8000.0, 800), Candidate("xs", 1000.0, 100), Candidate("m", 4000.0, 400),
              Candidate("s", 2000.0, 200)]
PSNR = {"xs": 28.0, "s": 30.5, "m": 31.0, "l": 31.1}
FLIP = {"xs": 0.20, "s": 0.12, "m": 0.10, "l": 0.09}
MS = {"xs": 2.0, "s": 5.0, "m": 12.0, "l": 30.0}


class Fakes:
    """time / obtain / measure callables from the tables above, recording what was obtained, in order."""

    def __init__(self, psnr=PSNR, flip=FLIP, ms=MS) -> None:
        self.psnr, self.flip, self.ms = psnr, flip, ms
        self.obtained: list[str] = []
        self.timed: list[str] = []

    def time_preset(self, preset: str) -> float:
        self.timed.append(preset)
        return self.ms[preset]

    def obtain(self, preset: str, progress) -> Obtained:
        self.obtained.append(preset)
        for step in range(1, 5):
            progress(step, 4, f"step {step}/4, loss 0.1")
        return Obtained(f"/ckpt/{preset}.pt", TRAINED, {"name": "fam-fit-x1", "version": preset})

    def measure(self, preset: str, obtained: Obtained) -> Measurement:
        return Measurement(psnr=self.psnr[preset], flip=self.flip[preset], ssim=0.9)

    def run(self, target: str, **kwargs):
        return run_ladder(CANDIDATES, Target.parse(target), family="fam", time_preset=self.time_preset,
                          obtain=self.obtain, measure=self.measure, **kwargs)


def statuses(result) -> dict[str, str]:
    return {rung.preset: rung.status for rung in result.rungs}


@pytest.mark.parametrize("target, chosen, obtained", [
    ("psnr=30", "s", ["xs", "s"]),  # the first that meets it ends the ladder
    ("psnr=28", "xs", ["xs"]),
    ("psnr=31.05", "l", ["xs", "s", "m", "l"]),
    ("flip=0.11", "m", ["xs", "s", "m"]),
    ("flip=0.2", "xs", ["xs"]),
    ("ms=15@64x64", "m", ["xs", "s", "m"]),  # l is over the budget: never trained; m has the best PSNR within it
    ("ms=4", "xs", ["xs"]),
    ("within=0.2", "m", ["l", "xs", "s", "m"]),  # the largest first (the bar: 30.9 dB), then from the smallest up
    ("within=5", "xs", ["l", "xs"]),
    ("within=0", "l", ["l", "xs", "s", "m"]),  # nothing smaller reaches the largest: the largest itself
])
def test_the_ladder_chooses_the_known_answer_and_trains_only_what_the_target_needs(target, chosen, obtained):
    fakes = Fakes()
    result = fakes.run(target)
    assert result.met and result.chosen.preset == chosen
    assert fakes.obtained == obtained
    assert fakes.timed == ["xs", "s", "m", "l"]  # every preset is timed, smallest first, before any training
    assert [rung.preset for rung in result.rungs] == ["xs", "s", "m", "l"]
    assert [rung.chosen for rung in result.rungs] == [rung.preset == chosen for rung in result.rungs]
    assert all(rung.ms_per_frame == MS[rung.preset] for rung in result.rungs)
    for rung in result.rungs:
        if rung.preset in obtained:
            assert rung.status == TRAINED and rung.psnr == PSNR[rung.preset]
        else:
            assert rung.status == SKIPPED and rung.psnr is None and "not trained" in rung.note


def test_skipped_presets_say_why():
    quality = Fakes().run("psnr=30")
    assert statuses(quality) == {"xs": TRAINED, "s": TRAINED, "m": SKIPPED, "l": SKIPPED}
    assert quality.rungs[2].note == "not needed: s already meets psnr=30; not trained"
    assert [rung.meets for rung in quality.rungs] == [False, True, None, None]
    assert quality.reason == "s: the smallest preset with validation PSNR >= 30 dB (30.50 dB)"

    budget = Fakes().run("ms=15@64x64")
    assert budget.rungs[3].note.startswith("over the time budget: 30 ms > 15 ms per frame at 64x64")
    assert [rung.meets for rung in budget.rungs] == [True, True, True, False]
    assert budget.reason.startswith("m: the best validation PSNR (31.00 dB) of the 3 preset(s) within 15 ms")

    within = Fakes().run("within=0.2")
    assert within.bar == pytest.approx(30.9)
    assert within.reason == ("m: the smallest preset with validation PSNR within 0.2 dB of the largest preset "
                             "(>= 30.90 dB) (31.00 dB)")
    assert within.rungs[3].meets is True


def test_a_time_budget_prefers_the_smaller_preset_on_equal_quality():
    fakes = Fakes(psnr={"xs": 28.0, "s": 31.0, "m": 31.0, "l": 32.0})
    assert fakes.run("ms=20").chosen.preset == "s"


def test_no_preset_meeting_the_target_is_no_choice_with_the_closest_named():
    fakes = Fakes()
    result = fakes.run("psnr=40")
    assert not result.met and result.chosen is None and fakes.obtained == ["xs", "s", "m", "l"]
    assert result.reason == "no preset meets validation PSNR >= 40 dB; the best, l, has 31.10 dB"
    assert not any(rung.chosen for rung in result.rungs)

    fakes = Fakes()
    result = fakes.run("ms=1@32x32")
    assert not result.met and fakes.obtained == []  # nothing fits the budget: nothing is trained
    assert result.reason == "no preset runs within 1 ms per frame at 32x32; the fastest, xs, takes 2 ms"

    assert Fakes().run("flip=0.01").reason == "no preset meets validation FLIP <= 0.01; the best, l, has FLIP 0.0900"


class FakeTracker:
    def __init__(self) -> None:
        self.params: dict = {}
        self.metrics: list[tuple[dict, int]] = []
        self.texts: dict[str, str] = {}

    def log_params(self, params):
        assert not set(params) & set(self.params), "a parameter logged twice"
        self.params.update(params)

    def log_metrics(self, metrics, step):
        self.metrics.append((metrics, step))

    def log_text(self, name, text):
        self.texts[name] = text


def test_every_measured_preset_is_logged_and_progress_ends_complete():
    tracker, reports = FakeTracker(), []
    Fakes().run("psnr=30", tracker=tracker, progress=lambda current, total, message: reports.append(
        (current, total, message)))
    assert tracker.params["xs.status"] == TRAINED and tracker.params["s.flops_per_pixel"] == 2000.0
    assert "m.status" not in tracker.params  # never obtained
    assert [(sorted(m), step) for m, step in tracker.metrics] == [
        (sorted(f"xs/{k}" for k in ("psnr", "ssim", "flip", "ms_per_frame", "flops_per_pixel", "params",
                                    "train_seconds")), 0),
        (sorted(f"s/{k}" for k in ("psnr", "ssim", "flip", "ms_per_frame", "flops_per_pixel", "params",
                                   "train_seconds")), 1)]
    assert all(0 <= current <= total for current, total, _ in reports)
    assert [current for current, _, _ in reports] == sorted(current for current, _, _ in reports)
    assert reports[-1][0] == reports[-1][1] and reports[-1][2].startswith("s: the smallest preset")
    assert any(message == "xs: step 2/4, loss 0.1" for _, _, message in reports)


def test_the_table_marks_the_choice_and_the_skipped_presets():
    result = Fakes().run("psnr=30")
    table = format_ladder(result)
    assert "| **s** (chosen) | 2k | 200 | 5 | 30.50 |" in table
    assert "| m | 4k | 400 | 12 | - | - | - | skipped: not needed: s already meets psnr=30; not trained | - |" in table
    assert table.endswith("choice: s: the smallest preset with validation PSNR >= 30 dB (30.50 dB)")


@pytest.mark.parametrize("text, expected", [
    ("psnr=30", Target("psnr", 30.0)),
    (" PSNR = 30.5 ", Target("psnr", 30.5)),
    ("flip=0.12", Target("flip", 0.12)),
    ("ms=20@128x128", Target("ms", 20.0, (128, 128))),
    ("ms=20@160x90", Target("ms", 20.0, (160, 90))),
    ("ms=20", Target("ms", 20.0, (256, 256))),
    ("within=0.2", Target("within", 0.2)),
])
def test_targets_parse(text, expected):
    assert Target.parse(text) == expected
    assert Target.parse(str(expected)) == expected


@pytest.mark.parametrize("text, message", [
    ("psnr", "is not one of psnr=DB"), ("speed=3", "is not one of"), ("psnr=abc", "'abc' is not a number"),
    ("ms=0", "ms must be positive"), ("flip=-1", "flip must be positive"), ("within=-0.1", "margin >= 0"),
    ("psnr=30@128x128", "only an ms target"), ("ms=20@big", "not WIDTHxHEIGHT"), ("psnr=inf", "finite"),
])
def test_bad_targets_are_value_errors_naming_the_forms(text, message):
    with pytest.raises(ValueError, match=message):
        Target.parse(text)


# --------------------------------------------------------------------------- reuse, with a real tiny training


class FakeStore:
    """An in-memory ModelStore: versions are dicts with tags and a copy of the checkpoint."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self.versions: list[dict] = []
        self.aliases: dict[tuple[str, str], str] = {}

    def _public(self, version: dict) -> dict:
        return {key: version[key] for key in ("name", "version", "uri")}

    def _find(self, version: dict) -> dict:
        return next(v for v in self.versions if (v["name"], v["version"]) == (version["name"], version["version"]))

    def find_version(self, tags):
        matches = [v for v in self.versions if all(v["tags"].get(k) == value for k, value in tags.items())]
        return self._public(matches[-1]) if matches else None

    def version_of_run(self, run_id):
        return None

    def download(self, version, folder):
        folder.mkdir(parents=True, exist_ok=True)
        return Path(shutil.copy2(self._find(version)["path"], folder / "checkpoint.pt"))

    def register(self, checkpoint, name, tags):
        number = str(sum(v["name"] == name for v in self.versions) + 1)
        path = self.folder / f"{name}-{number}.pt"
        shutil.copy2(checkpoint, path)
        self.versions.append({"name": name, "version": number, "uri": f"models:/{name}/{number}",
                              "tags": dict(tags), "path": path})
        return self._public(self.versions[-1])

    def tag_version(self, version, tags):
        self._find(version)["tags"].update(tags)

    def set_alias(self, name, alias, version):
        self.aliases[(name, alias)] = version


@pytest.fixture(scope="module")
def tiny_data(tmp_path_factory):
    return write_tiny_dataset(tmp_path_factory.mktemp("fit") / "data")


def tiny_config(data, out, **changes) -> FitConfig:
    values = dict(family=TINY_METHOD, data=str(data), target="within=100", presets=["default", "dropout"],
                  steps=2, crop=8, frames_per_sample=2, batch=2, warmup_steps=0, device="cpu",
                  out=str(out), time_at=(16, 16), timing_frames=2, timing_warmup=1, register_as="tiny-fit")
    values.update(changes)
    return FitConfig(**values)


def test_presets_are_reused_from_the_output_folder_and_from_the_registry(tiny_data, tmp_path, monkeypatch):
    store = FakeStore(tmp_path)
    first = fit(tiny_config(tiny_data, tmp_path / "fit"), store=store)
    # within: the largest (by FLOPs, then parameters; here equal, so the registry's order: dropout) trains first.
    assert statuses(first) == {"default": TRAINED, "dropout": TRAINED}
    assert first.chosen.preset == "default"
    assert store.aliases == {("tiny-fit", "fitted"): "1"}
    chosen = store.versions[0]
    assert chosen["tags"]["preset"] == "default" and chosen["tags"]["fit_key"] == first.info["fit_key"]
    assert chosen["tags"]["ms_per_frame_resolution"] == "16x16" and float(chosen["tags"]["ms_per_frame"]) > 0
    assert "validation_psnr" in chosen["tags"] and "metric.validation_flip" in chosen["tags"]
    assert (tmp_path / "fit" / "ladder.json").is_file() and (tmp_path / "fit" / "ladder.md").is_file()

    def no_training(*args, **kwargs):
        raise AssertionError("trained again")

    monkeypatch.setattr("model.training.train.train", no_training)
    again = fit(tiny_config(tiny_data, tmp_path / "fit"), store=store)
    assert statuses(again) == {"default": REUSED_CHECKPOINT, "dropout": REUSED_CHECKPOINT}
    assert [rung.psnr for rung in again.rungs] == [rung.psnr for rung in first.rungs]  # the same weights
    # The reused default found its registered version (same fit key); dropout, never registered, is now.
    assert [(v["name"], v["version"], v["tags"]["preset"]) for v in store.versions] == [
        ("tiny-fit", "1", "default"), ("tiny-fit", "2", "dropout")]
    assert store.aliases == {("tiny-fit", "fitted"): "1"}

    elsewhere = fit(tiny_config(tiny_data, tmp_path / "elsewhere"), store=store)
    assert statuses(elsewhere) == {"default": REUSED_REGISTRY, "dropout": REUSED_REGISTRY}
    assert [rung.psnr for rung in elsewhere.rungs] == [rung.psnr for rung in first.rungs]

    # Another setting is another key: nothing to reuse (and training is off limits here).
    with pytest.raises(AssertionError, match="trained again"):
        fit(tiny_config(tiny_data, tmp_path / "fit", seed=1), store=store)


def test_a_fit_stops_before_training_what_the_target_does_not_need(tiny_data, tmp_path, monkeypatch):
    import model.training.train as train_module  # model.fit imports train when it trains: patched here, seen there

    trained, original = [], train_module.train

    def counting(config, **kwargs):
        trained.append(config.method)
        return original(config, **kwargs)

    monkeypatch.setattr(train_module, "train", counting)
    result = fit(tiny_config(tiny_data, tmp_path / "fit", target="psnr=1"))  # no store: nothing registered
    assert trained == [f"{TINY_METHOD}:default"] and result.chosen.preset == "default"
    assert statuses(result) == {"default": TRAINED, "dropout": SKIPPED}
    assert result.info["registered"] is None


@pytest.mark.parametrize("changes, error, message", [
    ({"family": f"{TINY_METHOD}:default"}, ValueError, "takes a family"),
    ({"family": "identity"}, ValueError, "no trainable parameters"),
    ({"presets": ["huge"]}, KeyError, "no preset 'huge'"),
    ({"target": "speed=1"}, ValueError, "is not one of"),
    ({"validation_split": "test"}, ValueError, "no sequences in the validation split 'test'"),
    ({"crop": 64}, ValueError, "smaller than the 64x64 crop"),
    ({"alias": "latest"}, ValueError, "alias 'latest' is not usable"),
])
def test_a_fit_is_checked_before_anything_trains(tiny_data, tmp_path, changes, error, message):
    with pytest.raises(error, match=message):
        plan_fit(tiny_config(tiny_data, tmp_path / "bad", **changes))


@pytest.mark.parametrize("shipped", [True, False])
def test_a_fused_preset_is_timed_with_the_settings_its_training_will_run(tiny_data, tmp_path, monkeypatch, shipped):
    from model.fit.plan import plan_fit
    from model.fit.runner import _Fit

    timed = []

    def time_method(method, *args, **kwargs):
        timed.append((method.sample_mean_frames, method.stale_test_sigmas))
        return 1.0

    monkeypatch.setattr("model.fit.runner.time_method", time_method)
    config = tiny_config(tiny_data, tmp_path / "fit", family="fused", presets=["fast"], shipped_settings=shipped,
                         register_as=None)
    assert _Fit(plan_fit(config), None, None).time_preset("fast") == 1.0
    assert timed == ([(8, 0.5)] if shipped else [(0, 0.0)])
