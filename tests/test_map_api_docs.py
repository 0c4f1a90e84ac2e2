"""The public API is a reference: every public method of :class:`SprintMap` (those of the facade's
own modules) and of its service API (:class:`MapService`) has the numpydoc sections a newcomer
looks for: ``Parameters`` (naming every parameter), ``Returns`` (unless it returns None) and
``Raises`` (but for the few that raise nothing of the project's own, listed here)."""

from __future__ import annotations

import inspect
import re

import pytest

from sprint_map import MapService, SprintMap

#: The modules whose methods make SprintMap's API and its service's: every mixin of the facade.
OWN_MODULES = ("sprint_map.map", "sprint_map.facade.core", "sprint_map.facade.localizing",
               "sprint_map.facade.writing", "sprint_map.facade.upkeep", "sprint_map.facade.reading",
               "sprint_map.facade.positions", "sprint_map.facade.search",
               "sprint_map.facade.service", "sprint_map.facade.supply")

#: Methods that raise none of the project's errors (nor any other on purpose).
RAISES_NOTHING = {
    "SprintMap.cap_search_threads", "SprintMap.check", "SprintMap.close", "SprintMap.info", "SprintMap.is_current",
    "MapService.condition_prior", "MapService.drive_centring", "MapService.position_index",
    "MapService.select_merges", "MapService.shared_cache", "MapService.view",
}


def sections(doc: str) -> dict[str, str]:
    """The numpydoc sections of ``doc``: header -> the text under it."""
    lines = inspect.cleandoc(doc).splitlines()
    found: dict[str, str] = {}
    current: str | None = None
    for i, line in enumerate(lines):
        under = lines[i + 1].strip() if i + 1 < len(lines) else ""
        if line.strip() and under and set(under) == {"-"} and len(under) >= len(line.strip()):
            current = line.strip()
            found[current] = ""
        elif current is not None and not (line.strip() and set(line.strip()) == {"-"}):
            found[current] += line + "\n"
    return found


def missing_sections(owner: str, name: str, function: object) -> list[str]:
    """What the docstring of ``owner.name`` lacks, as readable complaints."""
    doc = inspect.getdoc(function) or ""
    found = sections(doc)
    signature = inspect.signature(function)  # type: ignore[arg-type]
    params = [p for p in signature.parameters.values() if p.name not in ("self", "cls")]
    problems = []
    if params:
        text = found.get("Parameters")
        if text is None:
            problems.append("no Parameters section")
        else:
            problems += [f"parameter {p.name!r} not described" for p in params
                         if not re.search(rf"(^|[\s,*]){re.escape(p.name)}\b", text)]
    if signature.return_annotation not in ("None", None) and "Returns" not in found:
        problems.append("no Returns section")
    if "Raises" not in found and f"{owner}.{name}" not in RAISES_NOTHING:
        problems.append("no Raises section")
    return problems


def public_methods(cls: type, modules: tuple[str, ...]) -> list[tuple[str, object]]:
    """The public methods (not properties) of ``cls`` defined in ``modules``."""
    out = []
    for name in sorted(dir(cls)):
        if name.startswith("_"):
            continue
        raw = inspect.getattr_static(cls, name)
        function = raw.__func__ if isinstance(raw, classmethod | staticmethod) else raw
        if inspect.isfunction(function) and function.__module__ in modules:
            out.append((name, function))
    return out


METHODS = ([("SprintMap", n, f) for n, f in public_methods(SprintMap, OWN_MODULES)]
           + [("MapService", n, f) for n, f in public_methods(MapService, OWN_MODULES)])


def test_the_api_is_walked():
    names = {f"{owner}.{name}" for owner, name, _ in METHODS}
    assert {"SprintMap.create", "SprintMap.ingest", "SprintMap.localize", "SprintMap.compact",
            "MapService.begin_drive", "MapService.commit_prepared"} <= names
    assert len(names) >= 35
    assert names >= RAISES_NOTHING, sorted(RAISES_NOTHING - names)


@pytest.mark.parametrize("owner, name, function", METHODS,
                         ids=[f"{o}.{n}" for o, n, _ in METHODS])
def test_public_method_has_its_numpydoc_sections(owner, name, function):
    problems = missing_sections(owner, name, function)
    assert not problems, f"{owner}.{name}: {', '.join(problems)}"


def _documented(x: int) -> int:
    """Twice ``x``.

    Parameters
    ----------
    x : int
        A number.

    Returns
    -------
    int
        ``2 * x``.

    Raises
    ------
    InputError
        Never, in fact.
    """
    return 2 * x


def _no_returns(x: int) -> int:
    """Twice ``x``.

    Parameters
    ----------
    x : int
        A number.
    """
    return 2 * x


def _unnamed(x: int, y: int) -> None:
    """Nothing.

    Parameters
    ----------
    x : int
        A number.

    Raises
    ------
    InputError
        Never.
    """


@pytest.mark.parametrize("function, problems", [
    (_documented, []),
    (_no_returns, ["no Returns section", "no Raises section"]),
    (_unnamed, ["parameter 'y' not described"]),
])
def test_a_missing_section_is_found(function, problems):
    assert missing_sections("t", function.__name__, function) == problems
