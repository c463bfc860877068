"""The package layout: every module of every package is at most 400 lines, every package folder has an
__init__.py whose docstring says what the subpackage is for and names each of its modules, as does the package's row
of docs/architecture.md, a module name is used once across the packages, and pyproject's package list installs every
package."""

from __future__ import annotations

import ast
import re
import tomllib
from collections import Counter
from pathlib import Path

import pytest
from setuptools import find_packages

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("stm", "experiments", "reports", "envs")
MAX_LINES = 400


def _package_dirs() -> list[Path]:
    """Every folder below a top-level package that holds Python modules."""
    dirs = set()
    for top in PACKAGES:
        for path in (REPO / top).rglob("*.py"):
            if "__pycache__" not in path.parts:
                dirs.add(path.parent)
    return sorted(dirs)


def _modules() -> list[Path]:
    return sorted(p for d in _package_dirs() for p in d.glob("*.py"))


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(REPO)))
def test_a_module_is_at_most_400_lines(path):
    lines = len(path.read_text().splitlines())
    assert lines <= MAX_LINES, f"{path.relative_to(REPO)}: {lines} lines; split it by topic"


@pytest.mark.parametrize("folder", _package_dirs(), ids=lambda p: str(p.relative_to(REPO)))
def test_a_package_says_what_it_is_for(folder):
    init = folder / "__init__.py"
    assert init.is_file(), f"{folder.relative_to(REPO)}: no __init__.py"
    doc = ast.get_docstring(ast.parse(init.read_text()))
    assert doc and len(doc.split()) >= 5, f"{init.relative_to(REPO)}: no docstring saying what the package is for"


def test_module_names_do_not_repeat_across_packages():
    names = Counter(p.name for p in _modules() if p.name not in ("__init__.py", "__main__.py"))
    repeated = {n: [str(p.relative_to(REPO)) for p in _modules() if p.name == n] for n, c in names.items() if c > 1}
    assert not repeated, f"module names used in several packages: {repeated}"


def test_pyproject_installs_every_package():
    config = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    found = set(find_packages(str(REPO), include=config["include"]))
    expected = {".".join(d.relative_to(REPO).parts) for d in _package_dirs()}
    assert expected <= found, f"not installed: {sorted(expected - found)}"


def _named_modules(folder: Path) -> list[str]:
    """The modules a package's docstring and its row of docs/architecture.md name: all but __init__, __main__ and
    the private ones."""
    return sorted(p.stem for p in folder.glob("*.py") if not p.name.startswith("_"))


@pytest.mark.parametrize("folder", _package_dirs(), ids=lambda p: str(p.relative_to(REPO)))
def test_a_package_docstring_names_each_of_its_modules(folder):
    doc = ast.get_docstring(ast.parse((folder / "__init__.py").read_text())) or ""
    missing = [m for m in _named_modules(folder) if not re.search(rf"(?<![\w.]){m}(?!\w)", doc)]
    assert not missing, f"{(folder / '__init__.py').relative_to(REPO)}: its docstring does not name {missing}"


def _architecture_rows() -> dict[str, str]:
    """docs/architecture.md's package table: `folder/` -> the row's text."""
    rows = re.findall(r"^\| `([\w/]+)/` \| (.*) \|$", (REPO / "docs" / "architecture.md").read_text(), re.M)
    return {folder: text for folder, text in rows}


@pytest.mark.parametrize("folder", _package_dirs(), ids=lambda p: str(p.relative_to(REPO)))
def test_architecture_names_each_module_of_a_package(folder):
    rows = _architecture_rows()
    key = folder.relative_to(REPO).as_posix()
    assert key in rows, f"docs/architecture.md has no row for `{key}/` in its package table"
    missing = [m for m in _named_modules(folder) if f"`{m}.py`" not in rows[key]]
    assert not missing, f"docs/architecture.md's row for `{key}/` does not name {[f'{m}.py' for m in missing]}"
