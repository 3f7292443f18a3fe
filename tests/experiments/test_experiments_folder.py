"""experiments/ stays out of the product: the installed packages never name it and never import from it."""

from __future__ import annotations

import ast
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("model", "core", "service", "workers", "cli", "client")


def test_the_package_list_does_not_install_experiments():
    include = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]["include"]
    assert not any(pattern.startswith("experiments") for pattern in include)
    assert not (ROOT / "experiments" / "__init__.py").exists()


def test_no_product_module_imports_experiments():
    offences = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
                names = ([alias.name for alias in node.names] if isinstance(node, ast.Import)
                         else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
                offences += [f"{path.relative_to(ROOT)}:{node.lineno} imports {name}" for name in names
                             if name == "experiments" or name.startswith("experiments.")]
    assert not offences, "\n".join(offences)
