"""Imports go one way: service -> storage -> engine (DESIGN.md "Layout", STYLE.md 1)."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
FORBIDDEN = {
    "engine": {
        "zarr",
        "trimesh",
        "fastapi",
        "pydantic",
        "pydantic_settings",
        "storage",
        "service",
        "uvicorn",
        "dask",
        "distributed",
    },
    # storage runs on the workers but knows nothing of Dask (service.cluster does)
    "storage": {"service", "fastapi", "uvicorn", "dask", "distributed"},
}


#: The installed names of the three packages (pyproject.toml: ``package-dir``).
PACKAGES = ("engine", "storage", "service")


def _top(module: str) -> str:
    """The top-level name of an import: ``rangefuse.engine.grid`` -> ``engine``, ``numpy.ma``
    -> ``numpy``."""
    parts = module.split(".")
    return parts[1] if parts[0] == "rangefuse" and len(parts) > 1 else parts[0]


def _absolute_imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.append(node.module)
    return names


def _imports(path: Path) -> set[str]:
    return {_top(name) for name in _absolute_imports(path)}


def _sources() -> list[Path]:
    folders = [*PACKAGES, "tests", "benchmarks"]
    return [p for folder in folders for p in (ROOT / folder).rglob("*.py")]


def test_packages_are_imported_by_their_installed_names() -> None:
    """``rangefuse.engine``, never a bare ``engine`` that only resolves from the checkout."""
    bare = {
        str(path.relative_to(ROOT)): sorted(
            n for n in _absolute_imports(path) if n.split(".")[0] in PACKAGES
        )
        for path in _sources()
    }
    assert {k: v for k, v in bare.items() if v} == {}


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_source_imports_go_one_way(package: str) -> None:
    offenders = {
        str(path.relative_to(ROOT)): sorted(_imports(path) & FORBIDDEN[package])
        for path in (ROOT / package).rglob("*.py")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_engine_loads_none_of_the_heavy_layers() -> None:
    code = (
        "import sys, rangefuse.engine, rangefuse.engine.synth;"
        "bad = sorted(m for m in ('zarr', 'trimesh', 'fastapi', 'pydantic', 'storage', 'service')"
        " if m in sys.modules or 'rangefuse.' + m in sys.modules);"
        "print(','.join(bad))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == ""


# --- a layout a newcomer can read (issue 17) ---------------------------------------------------

#: Most lines in a module, and in a function that is not a numba kernel.
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 100


def _is_kernel(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    """A numba kernel, or a factory that compiles one (a function that defines one)."""
    return any(
        isinstance(inner, ast.FunctionDef | ast.AsyncFunctionDef)
        and any("njit" in ast.unparse(d) for d in inner.decorator_list)
        for inner in ast.walk(node)
    )


def test_modules_and_functions_stay_readable() -> None:
    long_modules = {}
    long_functions = {}
    for path in _sources():
        source = path.read_text()
        name = str(path.relative_to(ROOT))
        if source.count("\n") > MAX_MODULE_LINES:
            long_modules[name] = source.count("\n")
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _is_kernel(node):
                lines = (node.end_lineno or node.lineno) - node.lineno + 1
                if lines > MAX_FUNCTION_LINES:
                    long_functions[f"{name}:{node.lineno} {node.name}"] = lines
    assert long_modules == {}
    assert long_functions == {}


def test_every_package_folder_is_installed() -> None:
    """pyproject.toml lists the packages (they are renamed under ``rangefuse``): a folder
    with an ``__init__.py`` missing there would be left out of ``pip install .``."""
    import tomllib

    listed = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]
    )
    found = {
        "rangefuse." + ".".join(init.parent.relative_to(ROOT).parts)
        for package in PACKAGES
        for init in (ROOT / package).rglob("__init__.py")
    }
    assert found == listed
