"""Docstrings say what, the contract and the cost, in at most 25 lines; why a design was
chosen is a decision record in ``docs/decisions.md``. Checked over every function and class of the
package, but for an explicit allow-list that only shrinks."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "sprint_map"
MAX_LINES = 25

#: Docstrings allowed over the limit, by ``path:qualified name``: none.
ALLOWED: set[str] = set()


def docstring_lengths(path: Path) -> dict[str, int]:
    """Lines of each function's and class's docstring in ``path``, by qualified name."""
    found: dict[str, int] = {}

    def visit(node: ast.AST, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
                name = prefix + child.name
                first = child.body[0] if child.body else None
                if (isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant)
                        and isinstance(first.value.value, str)):
                    assert first.end_lineno is not None
                    found[name] = first.end_lineno - first.lineno + 1
                visit(child, name + ".")
            else:
                visit(child, prefix)

    visit(ast.parse(path.read_text(), str(path)), "")
    return found


def all_lengths() -> dict[str, int]:
    return {f"{path.relative_to(PACKAGE).as_posix()}:{name}": lines
            for path in sorted(PACKAGE.rglob("*.py"))
            for name, lines in docstring_lengths(path).items()}


def test_no_docstring_is_longer_than_25_lines():
    over = {name: lines for name, lines in all_lengths().items()
            if lines > MAX_LINES and name not in ALLOWED}
    assert not over, f"docstrings over {MAX_LINES} lines (the why belongs in a record of docs/decisions.md)"\
                     f": {over}"


def test_the_allow_list_names_only_long_docstrings():
    """An entry whose docstring was trimmed, or whose function was renamed, must go."""
    lengths = all_lengths()
    stale = sorted(name for name in ALLOWED if lengths.get(name, 0) <= MAX_LINES)
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
