"""scripts/install.sh: its options, and the Blender step asking and installing through the pip it is given."""

from __future__ import annotations

import hashlib
import os
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "install.sh"


def blender_requirement(extra: str = "blender") -> str:
    with open(ROOT / "pyproject.toml", "rb") as file:
        return tomllib.load(file)["project"]["optional-dependencies"][extra][0]


def project_installed() -> bool:
    """The script's own stamp for this pyproject.toml: the project step then only checks (no install runs here)."""
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()[:16]
    return (ROOT / ".venv" / f".installed-{digest}").exists()


def run_with_pip(tmp_path: Path, shown_version: str | None, *args: str) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run the script with PIP pointing at a stub that answers `show bpy` with ``shown_version`` (None: not
    installed) and records every call."""
    calls = tmp_path / "calls"
    # a long answer, as pip's is: a reader that stops at the version line must not make the check fail
    shown = (f"echo 'Name: bpy'; echo 'Version: {shown_version}'; for i in $(seq 20000); do echo 'Location: x'; done"
             if shown_version else "exit 1")
    stub = tmp_path / "pip"
    stub.write_text(f'#!/usr/bin/env bash\necho "$*" >> {calls}\nif [ "$1" = show ]; then {shown}; fi\n')
    stub.chmod(0o755)
    result = subprocess.run(["bash", str(SCRIPT), *args], env={**os.environ, "PIP": str(stub)}, capture_output=True,
                            text=True)
    return result, calls.read_text().splitlines() if calls.exists() else []


def test_an_unknown_option_is_refused_before_anything_is_installed(tmp_path):
    result, calls = run_with_pip(tmp_path, None, "--blendr")
    assert result.returncode == 2
    assert "unknown option '--blendr'" in result.stderr and "--blender" in result.stderr
    assert calls == []


needs_the_project = pytest.mark.skipif(not project_installed(), reason="needs .venv installed by scripts/install.sh")


@needs_the_project
def test_blender_is_installed_at_the_extras_pin_without_its_dependencies(tmp_path):
    result, calls = run_with_pip(tmp_path, None, "--blender")
    assert result.returncode == 0, result.stderr
    assert calls == ["show bpy", f"install -q --no-deps {blender_requirement()}"]


@needs_the_project
def test_another_blender_version_is_replaced_by_the_pinned_one(tmp_path):
    result, calls = run_with_pip(tmp_path, "4.5.0", "--blender")
    assert result.returncode == 0, result.stderr
    assert calls[-1] == f"install -q --no-deps {blender_requirement()}"


@needs_the_project
def test_the_pinned_blender_already_there_is_only_checked(tmp_path):
    version = blender_requirement().split("==")[1]
    result, calls = run_with_pip(tmp_path, version, "--blender")
    assert result.returncode == 0, result.stderr
    assert calls == ["show bpy"]
    assert f"{blender_requirement()} is installed" in result.stdout


@needs_the_project
def test_without_the_option_blender_is_left_alone(tmp_path):
    result, calls = run_with_pip(tmp_path, None)
    assert result.returncode == 0, result.stderr
    assert calls == []


def test_an_unknown_blender_version_is_refused_before_anything_is_installed(tmp_path):
    result, calls = run_with_pip(tmp_path, None, "--blender=4.4")
    assert result.returncode == 2
    assert "unknown Blender version '4.4'" in result.stderr and "--blender=4.5" in result.stderr
    assert calls == []


@needs_the_project
@pytest.mark.parametrize("option, extra", [("--blender=4.5", "blender-4-5"), ("--blender=5", "blender")])
def test_a_blender_version_is_installed_at_its_extras_pin_replacing_the_other(tmp_path, option, extra):
    assert blender_requirement("blender-4-5").startswith("bpy==4.5.")
    other = "5.0.1" if extra == "blender-4-5" else "4.5.15"
    result, calls = run_with_pip(tmp_path, other, option)
    assert result.returncode == 0, result.stderr
    assert calls == ["show bpy", f"install -q --no-deps {blender_requirement(extra)}"]


@pytest.mark.parametrize("option", ["--browser", "--proxy"])
def test_the_debian_package_options_are_listed_among_the_options(tmp_path, option):
    result, _ = run_with_pip(tmp_path, None, option[:-1])
    assert result.returncode == 2 and option in result.stderr


@needs_the_project
@pytest.mark.parametrize(("option", "binary"), [("--browser", "chromium"), ("--proxy", "haproxy")])
def test_a_debian_package_already_on_the_path_is_only_checked(tmp_path, option, binary):
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name in (binary, "apt-get"):  # apt-get must not run: it would record a call
        (stubs / name).write_text(f'#!/usr/bin/env bash\necho "{name} $*" >> {tmp_path / "apt"}\n')
        (stubs / name).chmod(0o755)
    result = subprocess.run(["bash", str(SCRIPT), option], capture_output=True, text=True,
                            env={**os.environ, "PATH": f"{stubs}:{os.environ['PATH']}"})
    assert result.returncode == 0, result.stderr
    assert f"{binary} is installed" in result.stdout
    assert not (tmp_path / "apt").exists()
