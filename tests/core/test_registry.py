"""core.registry against a temporary MLflow store: model references, the checkpoint cache, aliases, errors."""

from __future__ import annotations

import pytest
import torch

from model.training.checkpoint import load_checkpoint
from core import registry as registry_module
from core.registry import ModelRef, UnknownModelError, get_registry, resolve_checkpoint
from tests.service.session_fixtures import MODEL_NAME, register_model, registry_settings, shared_registry, unique_name

__all__ = ["registry_settings"]  # fixture used by name


@pytest.mark.parametrize("text, expected", [
    ("models:/jnds-xs-x2/3", ModelRef("jnds-xs-x2", version="3")),
    ("models:/jnds-xs-x2@champion", ModelRef("jnds-xs-x2", alias="champion")),
    ("models:/jnds-xs-x2", ModelRef("jnds-xs-x2")),
])
def test_model_references_parse_and_print_back(text, expected):
    assert ModelRef.parse(text) == expected
    assert str(expected) == text


@pytest.mark.parametrize("text", ["jnds-xs-x2", "models:/", "models:/a/1/2", "models:/a@", "runs:/abc/model"])
def test_malformed_references_are_value_errors_that_show_the_forms(text):
    with pytest.raises(ValueError, match="models:/NAME/VERSION"):
        ModelRef.parse(text)


def _weights(path):
    return load_checkpoint(path)["model"]


def test_references_resolve_to_the_registered_checkpoints_and_are_cached(registry_settings, monkeypatch):
    store = shared_registry()
    by_version = resolve_checkpoint(f"models:/{MODEL_NAME}/2")
    by_alias = resolve_checkpoint(f"models:/{MODEL_NAME}@champion")  # champion -> 1
    latest = resolve_checkpoint(f"models:/{MODEL_NAME}")
    assert by_version == latest == registry_settings.data_dir / "models" / MODEL_NAME / "2" / "checkpoint.pt"
    assert by_alias == registry_settings.data_dir / "models" / MODEL_NAME / "1" / "checkpoint.pt"
    for path, version in ((by_version, "2"), (by_alias, "1")):
        expected = _weights(store.checkpoints[version])
        assert all(torch.equal(tensor, expected[name]) for name, tensor in _weights(path).items())

    # Cached: resolving again does not download (a registry that cannot download still answers).
    def no_download(*args, **kwargs):
        raise AssertionError("downloaded again")

    monkeypatch.setattr(registry_module, "download_registered_checkpoint", no_download)
    assert resolve_checkpoint(f"models:/{MODEL_NAME}/2") == by_version
    assert not any(registry_settings.data_dir.joinpath("staging").iterdir())  # no download leftovers


@pytest.mark.parametrize("ref, message", [
    ("models:/no-such-model/1", "model 'no-such-model' does not exist"),
    ("models:/no-such-model", "model 'no-such-model' does not exist"),
    (f"models:/{MODEL_NAME}/9", f"version 9 of model '{MODEL_NAME}' does not exist"),
    (f"models:/{MODEL_NAME}@nobody", f"model '{MODEL_NAME}' has no alias 'nobody' (aliases: champion)"),
])
def test_unknown_names_versions_and_aliases_are_key_errors_naming_them(registry_settings, ref, message):
    with pytest.raises(UnknownModelError) as caught:
        resolve_checkpoint(ref)
    assert isinstance(caught.value, KeyError) and str(caught.value) == message


def test_a_version_must_be_a_positive_integer(registry_settings):
    with pytest.raises(ValueError, match="model version 'abc' is not a positive integer"):
        get_registry().get_version(MODEL_NAME, "abc")
    with pytest.raises(ValueError, match="give a version or an alias"):
        get_registry().resolve_version(MODEL_NAME, version="1", alias="champion")


def test_models_list_with_versions_tags_metrics_and_aliases(registry_settings):
    registry = get_registry()
    summary = next(m for m in registry.list_models() if m.name == MODEL_NAME)
    assert summary.latest_version == "2" and summary.aliases == {"champion": "1"} and summary.versions == []

    detail = registry.get_model(MODEL_NAME)
    assert [v.version for v in detail.versions] == ["1", "2"]
    first, second = detail.versions
    assert (first.method, first.preset, first.scale, first.flops_per_pixel) == ("jnds", "xs", 2, 13416.0)
    assert first.params == int(first.tags["params"]) > 10_000
    assert first.metrics == {"validation_psnr": 21.5} and first.aliases == ["champion"]
    assert second.metrics == {"ms_per_frame": 3.25, "flip": 0.2} and second.aliases == []
    assert first.run_id and first.created_at is not None and first.tags["preset"] == "xs"


def test_aliases_are_set_moved_read_and_deleted(registry_settings):
    name = unique_name("aliases")
    register_model(name, versions=2)
    registry = get_registry()
    assert registry.set_alias(name, "staging", "1").version == "1"
    assert registry.set_alias(name, "staging", 2).version == "2"  # moved
    assert registry.get_alias(name, "staging").aliases == ["staging"]
    assert registry.get_model(name).aliases == {"staging": "2"}
    registry.delete_alias(name, "staging")
    with pytest.raises(UnknownModelError, match="has no alias 'staging'"):
        registry.get_alias(name, "staging")
    with pytest.raises(UnknownModelError, match="has no alias 'staging'"):
        registry.delete_alias(name, "staging")  # MLflow itself would ignore it
    with pytest.raises(UnknownModelError, match=f"version 7 of model '{name}' does not exist"):
        registry.set_alias(name, "staging", "7")
    with pytest.raises(ValueError, match="reserved"):
        registry.set_alias(name, "latest", "1")
