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
    },
    "storage": {"service", "fastapi", "uvicorn"},
}


def _imports(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(alias.name.split(".")[0] for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            names.add(node.module.split(".")[0])
    return names


@pytest.mark.parametrize("package", sorted(FORBIDDEN))
def test_source_imports_go_one_way(package: str) -> None:
    offenders = {
        str(path.relative_to(ROOT)): sorted(_imports(path) & FORBIDDEN[package])
        for path in (ROOT / package).rglob("*.py")
    }
    assert {k: v for k, v in offenders.items() if v} == {}


def test_importing_engine_loads_none_of_the_heavy_layers() -> None:
    code = (
        "import sys, engine, engine.synth;"
        "bad = sorted(m for m in ('zarr', 'trimesh', 'fastapi', 'pydantic', 'storage', 'service')"
        " if m in sys.modules);"
        "print(','.join(bad))"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
    )
    assert out.stdout.strip() == ""
