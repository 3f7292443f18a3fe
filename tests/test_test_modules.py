"""Rules of the test suite itself: test modules share helpers only through builders and fixture modules.

No test module imports from another ``test_*.py`` module (shared builders live in ``tests/builders.py``, shared
fixtures in ``conftest.py`` and ``*_fixtures.py``), and no module defines its own copy of a builder.
"""

from __future__ import annotations

import ast
from pathlib import Path

TESTS = Path(__file__).resolve().parent
BUILDERS = TESTS / "builders.py"


def _modules() -> list[Path]:
    return sorted(path for path in TESTS.rglob("*.py") if "__pycache__" not in path.parts)


def _dotted(path: Path) -> str:
    parts = path.relative_to(TESTS.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported_modules(text: str, module: str) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in the source ``text`` of ``module`` (dotted), relative imports
    resolved; ``from X import Y`` gives both X and X.Y (Y may be a module)."""
    package = module.split(".")[:-1]
    found = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package[:len(package) - (node.level - 1)]
                base = ".".join(anchor + ([base] if base else []))
            found.append((node.lineno, base))
            found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
    return found


def _from_test_modules(text: str, module: str) -> list[tuple[int, str]]:
    return [(line, name) for line, name in _imported_modules(text, module)
            if name.startswith("tests.") and name.rsplit(".", 1)[-1].startswith("test_")]


def test_no_test_module_imports_from_another_test_module():
    offences = [f"{path.relative_to(TESTS.parent)}:{line} imports {name}" for path in _modules()
                for line, name in _from_test_modules(path.read_text(), _dotted(path))]
    assert not offences, "import shared helpers from tests.builders (or a fixture module):\n" + "\n".join(offences)


def test_builders_are_defined_once():
    builders = {node.name for node in ast.parse(BUILDERS.read_text()).body
                if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and not node.name.startswith("_")}
    copies = [f"{path.relative_to(TESTS.parent)}:{node.lineno} defines {node.name}" for path in _modules()
              if path != BUILDERS for node in ast.parse(path.read_text()).body
              if isinstance(node, (ast.FunctionDef, ast.ClassDef)) and node.name in builders]
    assert not copies, "use the builder from tests.builders instead of a copy:\n" + "\n".join(copies)


def test_the_rule_sees_absolute_relative_and_module_imports_of_test_modules():
    text = ("from tests.model.io.test_frames import make_frame\nfrom .test_exr import zero_bomb\n"
            "from tests.model import test_dataset\nimport tests.service.test_cli\n"
            "from tests.builders import make_frame\nfrom .training_fixtures import TINY_METHOD\n")
    found = {name for _, name in _from_test_modules(text, "tests.model.test_probe")}
    assert {"tests.model.io.test_frames", "tests.model.test_exr", "tests.model.test_dataset",
            "tests.service.test_cli"} <= found
    assert not any(name.startswith(("tests.builders", "tests.model.training_fixtures")) for name in found)
