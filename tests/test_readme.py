"""README.md is the product's front page: short, its first commands on the first screen, its settings table and
its links true to the repository, and its test command the one CI runs."""

from __future__ import annotations

import re
import shlex
from pathlib import Path

import pytest
from pydantic_core import PydanticUndefined

from core.settings import Settings

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
CI_RUN = ROOT / ".ci" / "run"

MAX_LINES = 600
FIRST_SCREEN = 60  # the set-up, test and first denoise commands must be within these lines
SETUP_COMMAND = "bash scripts/setup.sh"
TEST_COMMAND = "bash scripts/test.sh"
SETTINGS_HEADER = "| variable | default | meaning |"

FENCE = re.compile(r"^```.*?^```[ \t]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")
LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
BACKTICKED = re.compile(r"`([^`]*)`")


def _lines() -> list[str]:
    return README.read_text(encoding="utf-8").splitlines()


def _commands(lines: list[str]) -> list[str]:
    """Each line inside a fenced code block, its trailing comment cut off and whitespace stripped."""
    commands, inside = [], False
    for line in lines:
        if line.lstrip().startswith("```"):
            inside = not inside
            continue
        if inside:
            command = line.split(" #", 1)[0].strip()
            if command:
                commands.append(command)
    return commands


def _prose(text: str) -> str:
    """The README without its code blocks and inline code, where no link is a link."""
    return INLINE_CODE.sub("", FENCE.sub("", text))


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation but '-' and '_' dropped, spaces to '-'."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def _anchors(text: str) -> set[str]:
    headings = [line.lstrip("#").strip() for line in FENCE.sub("", text).splitlines() if line.startswith("#")]
    return {_slug(heading) for heading in headings}


# --- (a) length --------------------------------------------------------------------------------------------------


def test_readme_has_at_most_600_lines():
    count = len(_lines())
    assert count <= MAX_LINES, f"README.md has {count} lines; the front page holds at most {MAX_LINES}"


# --- (b) the first screen ----------------------------------------------------------------------------------------


def test_setup_test_and_first_denoise_commands_are_on_the_first_screen():
    first = _commands(_lines()[:FIRST_SCREEN])
    assert SETUP_COMMAND in first, f"'{SETUP_COMMAND}' must be a command within the first {FIRST_SCREEN} lines"
    assert TEST_COMMAND in first, f"'{TEST_COMMAND}' must be a command within the first {FIRST_SCREEN} lines"
    streams = [command for command in first if re.match(r"^(\S*/)?denoiser stream\s", command)]
    assert streams, f"a 'denoiser stream' command must be within the first {FIRST_SCREEN} lines"
    assert all("--model" in command and "--out" in command for command in streams), streams


# --- (c) the settings table --------------------------------------------------------------------------------------


def _settings_rows() -> list[list[str]]:
    """The cells of the settings table's rows (the table whose header is SETTINGS_HEADER)."""
    lines = _lines()
    assert SETTINGS_HEADER in lines, f"README.md has no settings table (header {SETTINGS_HEADER!r})"
    rows = []
    for line in lines[lines.index(SETTINGS_HEADER) + 2:]:
        if not line.startswith("|"):
            break
        cells = [cell.strip() for cell in re.split(r"(?<!\\)\|", line.strip())[1:-1]]
        rows.append(cells)
    return rows


def _variable(cell: str) -> str:
    return cell.strip().strip("`").strip()


def default_text(value: object) -> str:
    """A setting's default in the README's normalised form.

    The README's default cell starts with this text in backticks (anything after the backticks, such as
    "(2 GiB)", is a note for the reader):
    - unset (``None``): ``none``; a required field: ``required``;
    - a bool: ``true`` / ``false``;
    - a path inside the repository (a default computed from where the code runs): the path relative to the
      repository root, with '/' (``var``); any other path as it is;
    - anything else: ``str(value)`` (``20.0``, ``2147483648``, ``redis://127.0.0.1:6379/0``, ``half``).
    """
    if value is PydanticUndefined:
        return "required"
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Path):
        if not value.is_absolute():
            return value.as_posix()
        try:
            return value.resolve().relative_to(ROOT.resolve()).as_posix()
        except ValueError:
            return str(value)
    return str(getattr(value, "value", value))


def _field_default(field) -> object:
    return field.default_factory() if field.default_factory is not None else field.default


def test_settings_table_lists_exactly_the_settings_fields():
    expected = {f"DENOISER_{name.upper()}" for name in Settings.model_fields}
    listed = [_variable(row[0]) for row in _settings_rows()]
    duplicates = sorted({name for name in listed if listed.count(name) > 1})
    missing = sorted(expected - set(listed))
    extra = sorted(set(listed) - expected)
    assert not (missing or extra or duplicates), (
        f"the README's settings table must list DENOISER_<FIELD> for every field of core.settings.Settings; "
        f"missing: {', '.join(missing) or 'none'}; extra: {', '.join(extra) or 'none'}; "
        f"listed twice: {', '.join(duplicates) or 'none'}")


def test_settings_table_defaults_match_the_fields():
    by_variable = {_variable(row[0]): row for row in _settings_rows()}
    wrong = []
    for name, field in Settings.model_fields.items():
        row = by_variable.get(f"DENOISER_{name.upper()}")
        if row is None:
            continue  # reported by the test above
        assert len(row) == 3, f"settings row of {name} must have 3 cells (variable, default, meaning): {row}"
        shown = BACKTICKED.search(row[1])
        text = shown.group(1) if shown else row[1]
        expected = default_text(_field_default(field))
        if text != expected:
            wrong.append(f"DENOISER_{name.upper()}: README says {text!r}, Settings has {expected!r}")
        if not row[2]:
            wrong.append(f"DENOISER_{name.upper()}: no meaning given")
    assert not wrong, "the settings table's defaults differ from core.settings.Settings:\n" + "\n".join(wrong)


def test_default_text_normalises_as_documented(tmp_path):
    assert default_text(None) == "none"
    assert default_text(PydanticUndefined) == "required"
    assert default_text(False) == "false"
    assert default_text(20.0) == "20.0"
    assert default_text(2 * 1024**3) == "2147483648"
    assert default_text(ROOT / "var") == "var"
    assert default_text(Path("var")) == "var"
    assert default_text(tmp_path) == str(tmp_path)


# --- (d) links and pictures --------------------------------------------------------------------------------------


def _relative_targets() -> list[str]:
    targets = LINK.findall(_prose(README.read_text(encoding="utf-8")))
    return [target for target in targets if not re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE)]


def test_every_relative_link_and_picture_exists():
    targets = _relative_targets()
    assert any(target.endswith(".png") for target in targets), "the README shows no picture"
    missing = sorted({target for target in targets if not target.startswith("#")
                      and not (ROOT / target.split("#", 1)[0]).exists()})
    assert not missing, "README.md links to paths that are not in the repository:\n" + "\n".join(missing)


def test_every_in_page_link_names_a_heading():
    text = README.read_text(encoding="utf-8")
    anchors = _anchors(text)
    broken = sorted({target for target in _relative_targets() if target.startswith("#")
                     and target[1:] not in anchors})
    assert not broken, f"README.md links to headings it does not have: {', '.join(broken)}"


def test_the_link_parser_finds_links_and_pictures_but_not_code():
    text = ("See [a](docs/a.md) and ![pic](docs/p.png \"title\"), [b](https://x.org), [c](#c-d).\n"
            "`[not](a/link.md)`\n```\n[nor](this.md)\n```\n")
    assert LINK.findall(_prose(text)) == ["docs/a.md", "docs/p.png", "https://x.org", "#c-d"]
    assert _slug("Bringing a renderer's frames") == "bringing-a-renderers-frames"


# --- (e) CI runs the README's test command -----------------------------------------------------------------------


def _ci_commands() -> list[str]:
    """.ci/run's commands: its lines but the shebang, comments, blank lines, `set` options and the `cd` to the
    repository root."""
    commands = []
    for line in CI_RUN.read_text(encoding="utf-8").splitlines():
        line = line.strip()
        if not line or line.startswith("#") or line.startswith("set ") or line.startswith("cd "):
            continue
        commands.append(line)
    return commands


def test_ci_runs_exactly_the_readme_test_command():
    readme_tests = [command for command in _commands(_lines()[:FIRST_SCREEN])
                    if shlex.split(command)[:2] == ["bash", "scripts/test.sh"]]
    assert readme_tests, "the README's first screen has no test command"
    test_command = readme_tests[0]
    assert test_command == TEST_COMMAND, f"the README's first test command is {test_command!r}"
    assert _ci_commands() == [test_command], (
        f".ci/run must run exactly the README's test command {test_command!r}; it runs {_ci_commands()}")


@pytest.mark.parametrize("script", ["scripts/setup.sh", "scripts/test.sh"])
def test_the_first_screen_scripts_exist(script):
    assert (ROOT / script).is_file(), f"the README's first command runs {script}, which is missing"
