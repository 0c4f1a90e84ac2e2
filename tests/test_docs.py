"""The documentation keeps up with the code (model: sqlite-utils' ``tests/test_docs.py``).

- every command of the CLI (walking the click group) is documented, and ``docs/cli.md`` is
  exactly what ``sprint_map.cli.reference`` generates from the commands' ``--help``;
- every exit code of ``sprint_map/errors.py`` is in ``docs/cli.md``'s table;
- every reference to a page of ``docs/`` names a page that exists, and a quoted section after
  it (``docs/x.md``, "Section") names a heading or a bold paragraph label of that page;
- ``docs/architecture.md`` stays the design: at most ~500 lines, benchmark tables elsewhere.
"""

from __future__ import annotations

import difflib
import re
from pathlib import Path

import pytest

from sprint_map import errors
from sprint_map.cli import reference as cli_reference

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
CLI_MD = DOCS / "cli.md"
README = ROOT / "README.md"
COMMANDS = [path for path, _ in cli_reference.commands()]
ERRORS = sorted(
    (cls for cls in vars(errors).values()
     if isinstance(cls, type) and issubclass(cls, errors.SprintMapError)),
    key=lambda cls: cls.exit_code)


@pytest.mark.parametrize("path", COMMANDS)
def test_every_command_is_documented(path):
    documented = {line[3:].strip() for line in CLI_MD.read_text().splitlines()
                  if line.startswith("## ")}
    assert path in documented or f"`{path}`" in README.read_text(), (
        f"`{path}` is not documented: regenerate docs/cli.md with "
        f"`{cli_reference.REGENERATE}` (it adds a '## {path}' section with the command's "
        "--help; give the command a docstring with an example first), and add a line for it "
        "to README.md's 'Using it' block")


def test_cli_reference_is_current():
    expected = cli_reference.render()
    current = CLI_MD.read_text(encoding="utf-8")
    diff = "".join(difflib.unified_diff(current.splitlines(True), expected.splitlines(True),
                                        "docs/cli.md", "generated", n=1))
    assert current == expected, (
        f"docs/cli.md differs from the CLI's help texts and exit codes: run "
        f"`{cli_reference.REGENERATE}` and commit docs/cli.md.\n{diff[:3000]}")


@pytest.mark.parametrize("cls", ERRORS, ids=lambda cls: cls.__name__)
def test_every_exit_code_is_documented(cls):
    row = re.compile(rf"^\| {cls.exit_code} \| `{cls.__name__}` \| \S", re.M)
    assert row.search(CLI_MD.read_text()), (
        f"exit code {cls.exit_code} ({cls.__name__}) is not in docs/cli.md's 'Exit codes' "
        f"table: give the class a docstring (its first paragraph is the row's meaning) and run "
        f"`{cli_reference.REGENERATE}`")


def test_exit_codes_are_distinct():
    codes = [cls.exit_code for cls in ERRORS] + list(cli_reference.GENERAL_EXIT_CODES)
    assert len(codes) == len(set(codes)), "two error kinds share an exit code"


# --- references between documents ---------------------------------------------------------

# docs/page.md, optionally followed on the same line by a quoted section (which may wrap once).
REFERENCE = re.compile(r"docs/([\w.-]+\.md)(?:[`, (]{0,6}\"([^\"\n]{1,80}(?:\n[^\"\n]{1,80})?)\")?")


def _sources() -> list[Path]:
    files = [README, *DOCS.glob("*.md"), *(ROOT / "sprint_map").rglob("*.py"),
             *(ROOT / "tools").glob("*.py"), *(ROOT / "tests").rglob("*.py")]
    return [f for f in files if f.name != "test_docs.py"]


def _anchors(page: Path) -> list[str]:
    """The page's headings and bold paragraph labels, backticks removed."""
    text = page.read_text(encoding="utf-8")
    found = re.findall(r"^#+ (.+)$", text, re.M) + re.findall(r"^\*\*(.+?)\*\*", text, re.M)
    return [_plain(a) for a in found]


def _plain(text: str) -> str:
    return " ".join(text.replace("`", "").replace("#", " ").split())


def _references() -> list[tuple[str, str, str | None]]:
    refs = []
    for source in _sources():
        text = source.read_text(encoding="utf-8")
        for match in REFERENCE.finditer(text):
            line = text.count("\n", 0, match.start()) + 1
            refs.append((f"{source.relative_to(ROOT)}:{line}", match.group(1), match.group(2)))
    return refs


def test_references_to_docs_resolve():
    missing = []
    for where, page, section in _references():
        target = DOCS / page
        if not target.is_file():
            missing.append(f"{where}: docs/{page} does not exist")
        elif section is not None and not any(
                a.startswith(_plain(section)) for a in _anchors(target)):
            missing.append(f"{where}: docs/{page} has no section \"{_plain(section)}\"")
    assert not missing, "dangling references:\n" + "\n".join(missing)


def test_the_reference_check_sees_references():
    """The scan above finds references in every form the sources use (guards the regex)."""
    refs = {(page, section) for _, page, section in _references()}
    assert ("architecture.md", "Failure model") in refs  # ``docs/...``, "..." in a docstring
    assert ("hmm.md", "The HMM") in refs  # docs/... ("...")
    assert any(section is None for _, section in refs)


# --- the design page stays the design -------------------------------------------------------


def test_architecture_is_the_design_only():
    text = (DOCS / "architecture.md").read_text(encoding="utf-8")
    lines = text.count("\n")
    assert lines <= 520, (
        f"docs/architecture.md has {lines} lines: it is the design (layers, on-disk format, "
        "commit protocol, failure model, data flow) in ~500; move reference material to "
        "docs/hmm.md, docs/service.md or docs/frontend.md and figures to docs/benchmarks.md")
    # A measured table has a column of timings, rates or percentages.
    measured = [row for row in text.splitlines() if row.startswith("|")
                and re.search(r"\|\s*[\d.,]+\s*(ms|µs|s|%|/s|MB|GB)\s*\|", row)]
    assert not measured, (
        "benchmark rows in docs/architecture.md (move them to docs/benchmarks.md with the "
        "command that produced them):\n" + "\n".join(measured))
