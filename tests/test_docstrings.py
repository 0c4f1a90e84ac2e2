"""Docstrings say what, the contract and the cost, in at most 25 lines of prose before their
numpydoc sections (``Parameters``, ``Returns``, ``Raises``, ``Examples``, ...), 80 lines in all;
why a design was chosen is a decision record in ``docs/decisions.md``. Checked over every function
and class of the package, but for an explicit allow-list that only shrinks."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "sprint_map"
#: Lines of prose before the first numpydoc section, and of the whole docstring.
MAX_LINES = 25
MAX_TOTAL_LINES = 80
#: The numpydoc section headers that end the prose (each underlined by dashes).
SECTIONS = ("Parameters", "Returns", "Raises", "Yields", "Examples", "See Also", "Notes")

#: Docstrings allowed over the limit, by ``path:qualified name``: none.
ALLOWED: set[str] = set()


def prose_lines(text: str, total: int) -> int:
    """Lines of a docstring (``total`` in all) before its first numpydoc section: a line
    naming one of :data:`SECTIONS` over a line of dashes."""
    lines = text.splitlines()
    for i, line in enumerate(lines[:-1]):
        under = lines[i + 1].strip()
        if line.strip() in SECTIONS and under and set(under) == {"-"}:
            return i
    return total


def docstring_lengths(path: Path, *, prose: bool = False) -> dict[str, int]:
    """Lines of each function's and class's docstring in ``path``, by qualified name (with
    ``prose``, only the lines before its first numpydoc section)."""
    found: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = prefix + child.name
                first = child.body[0] if child.body else None
                if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                        and isinstance(first.value.value, str)):
                    assert first.end_lineno is not None
                    total = first.end_lineno - first.lineno + 1
                    found[name] = (prose_lines(first.value.value, total)
                                   if prose else total)
                visit(child, name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(), str(path)), "")
    return found


def all_lengths(*, prose: bool = False) -> dict[str, int]:
    return {f"{path.relative_to(PACKAGE).as_posix()}:{name}": lines
            for path in sorted(PACKAGE.rglob("*.py"))
            for name, lines in docstring_lengths(path, prose=prose).items()}


def test_no_docstring_has_more_than_25_lines_of_prose():
    over = {name: lines for name, lines in all_lengths(prose=True).items()
            if lines > MAX_LINES and name not in ALLOWED}
    assert not over, f"docstrings over {MAX_LINES} lines before their sections (the why "\
                     f"belongs in a record of docs/decisions.md): {over}"


def test_no_docstring_is_longer_than_80_lines():
    over = {name: lines for name, lines in all_lengths().items()
            if lines > MAX_TOTAL_LINES and name not in ALLOWED}
    assert not over, f"docstrings over {MAX_TOTAL_LINES} lines in all: {over}"


def test_the_allow_list_names_only_long_docstrings():
    """An entry whose docstring was trimmed, or whose function was renamed, must go."""
    prose, total = all_lengths(prose=True), all_lengths()
    stale = sorted(name for name in ALLOWED
                   if prose.get(name, 0) <= MAX_LINES and total.get(name, 0) <= MAX_TOTAL_LINES)
    assert not stale, f"trimmed or gone: remove from ALLOWED: {stale}"


@pytest.mark.parametrize("source, expected", [
    ('def f():\n    """one\n    two"""\n', {"f": 2}),
    ('class C:\n    """c"""\n    def m(self):\n        """a\n\n        b\n        """\n',
     {"C": 1, "C.m": 4}),
    ('def f():\n    x = 1\n    """not a docstring"""\n', {}),
])
def test_docstring_lengths_are_counted_per_qualified_name(tmp_path, source, expected):
    path = tmp_path / "m.py"
    path.write_text(source)
    assert docstring_lengths(path) == expected


@pytest.mark.parametrize("source, whole, prose", [
    # The prose ends at the first section header over its dashes.
    ('def f():\n    """one\n\n    Parameters\n    ----------\n    x : int\n    """\n',
     {"f": 6}, {"f": 2}),
    # A section name in the prose, or dashes under another word, ends nothing.
    ('def f():\n    """Returns\n    the end\n    words\n    -----\n    """\n',
     {"f": 5}, {"f": 5}),
    ('class C:\n    def m(self):\n        """a\n\n        Examples\n        --------\n'
     '        >>> 1\n        1\n        """\n', {"C.m": 7}, {"C.m": 2}),
])
def test_prose_is_counted_before_the_first_section(tmp_path, source, whole, prose):
    path = tmp_path / "m.py"
    path.write_text(source)
    assert docstring_lengths(path) == whole
    assert docstring_lengths(path, prose=True) == prose
