"""core.settings: the one settings object; its paths never depend on the folder a process runs in."""

from __future__ import annotations

from pathlib import Path

import core.settings as settings_module
from core.settings import Settings, default_data_dir


def test_the_default_data_folder_is_the_checkouts_var_else_the_users_data_folder(tmp_path, monkeypatch):
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    (checkout / "pyproject.toml").write_text("")
    monkeypatch.setattr(settings_module, "PROJECT_ROOT", checkout)
    assert default_data_dir() == checkout / "var"

    installed = tmp_path / "site-packages"  # an installed package: no pyproject.toml beside core/
    installed.mkdir()
    monkeypatch.setattr(settings_module, "PROJECT_ROOT", installed)
    monkeypatch.setenv("XDG_DATA_HOME", str(tmp_path / "xdg"))
    assert default_data_dir() == tmp_path / "xdg" / "denoiser"
    monkeypatch.setenv("XDG_DATA_HOME", "relative/ignored")  # the XDG rule: only an absolute path counts
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert default_data_dir() == tmp_path / "home" / ".local" / "share" / "denoiser"


def test_this_checkout_defaults_to_its_own_var(monkeypatch):
    monkeypatch.delenv("DENOISER_DATA_DIR", raising=False)
    monkeypatch.delenv("DENOISER_TRACKING_URI", raising=False)
    root = Path(__file__).resolve().parents[2]
    settings = Settings()
    assert settings.data_dir == root / "var"
    assert settings.resolved_tracking_uri() == f"sqlite:///{root / 'var' / 'mlflow' / 'mlflow.db'}"


def test_relative_paths_are_made_absolute_once_from_the_current_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DENOISER_DATA_DIR", "data")
    monkeypatch.setenv("DENOISER_PRETRAINED_DIR", "shipped")
    monkeypatch.setenv("DENOISER_TRACKING_URI", "sqlite:///store/mlflow.db")
    settings = Settings()
    assert settings.data_dir == tmp_path / "data" and settings.pretrained_dir == tmp_path / "shipped"
    assert settings.resolved_tracking_uri() == f"sqlite:///{tmp_path / 'store' / 'mlflow.db'}"
    monkeypatch.setenv("DENOISER_TRACKING_URI", "http://mlflow:5000")  # a server's URI is taken as given
    assert Settings().resolved_tracking_uri() == "http://mlflow:5000"


def test_every_setting_says_what_it_is_in_one_line():
    # The README's settings table is made from these descriptions.
    for name, field in Settings.model_fields.items():
        assert field.description and "\n" not in field.description, name
