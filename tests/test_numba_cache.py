"""The engine's kernels are cached under a stamp of every engine file (engine/_numba_cache.py):
a change to a file whose kernels others call compiles those others again, instead of
loading their builds with the old code inside."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import numba
import rangefuse.engine
from rangefuse.engine._numba_cache import ENGINE_DIR, engine_source_stamp, source_stamp


def _engine_kernels() -> list[numba.core.registry.CPUDispatcher]:
    import importlib
    import pkgutil

    found = []
    for info in pkgutil.walk_packages(rangefuse.engine.__path__, "rangefuse.engine."):
        module = importlib.import_module(info.name)
        for value in vars(module).values():
            cache = getattr(value, "_cache", None)
            if isinstance(value, numba.core.registry.CPUDispatcher) and hasattr(cache, "_impl"):
                found.append(value)
    return found


def test_every_cached_engine_kernel_is_stamped_with_the_whole_engine() -> None:
    kernels = _engine_kernels()
    assert len(kernels) > 20  # the fusion, allocation, meshing ... kernels
    assert any(".synth." in k.py_func.__module__ for k in kernels)  # the renderer's too
    for kernel in kernels:
        locator = kernel._cache._impl.locator
        assert type(locator).__name__ == "_EngineLocator", kernel
        assert locator.get_source_stamp() == engine_source_stamp()
        assert Path(locator.get_cache_path()).is_dir()  # numba's folder for it, as before


def test_a_tests_kernel_is_stamped_with_the_engine_and_its_own_file() -> None:
    """A test's helper kernel compiles engine kernels into it (tests/test_lidar.py's compares
    the engine's beam rows found two ways): an engine change must compile it again too."""
    from tests.test_lidar import _rows_two_ways

    locator = _rows_two_ways._cache._impl.locator
    assert type(locator).__name__ == "_EngineLocator"
    engine, own = locator.get_source_stamp()
    assert engine == engine_source_stamp()
    assert own == locator._inner.get_source_stamp()  # numba's stamp of the test file


def test_the_stamp_changes_with_any_engine_file(tmp_path) -> None:
    copy = tmp_path / "engine"
    shutil.copytree(ENGINE_DIR, copy, ignore=shutil.ignore_patterns("__pycache__"))
    assert source_stamp(copy) == engine_source_stamp()
    callee = copy / "_sensor_kernels.py"  # called by fusion.py's kernels, not defining them
    callee.write_text(callee.read_text() + "\n# changed\n")
    assert source_stamp(copy) != engine_source_stamp()


def test_a_change_to_a_called_file_compiles_its_callers_again(tmp_path) -> None:
    """A copy of the engine, imported as ``rangefuse.engine``: a kernel compiled, then loaded
    from the cache; after a change to another engine file only, compiled again."""
    root = tmp_path / "src"
    shutil.copytree(ENGINE_DIR, root / "rangefuse" / "engine",
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    (root / "rangefuse" / "__init__.py").write_text("")
    script = (
        "import numpy as np\n"
        "from numba.core import event\n"
        "compiled = []\n"
        "class L(event.Listener):\n"
        "    def on_start(self, ev): compiled.append(1)\n"
        "    def on_end(self, ev): pass\n"
        "event.register('numba:compile', L())\n"
        "import rangefuse.engine\n"
        "from rangefuse.engine.grid import pack_keys\n"
        "pack_keys(np.zeros((1, 3), np.int64))\n"
        "print(rangefuse.engine.__file__, 'compiled' if compiled else 'loaded')\n"
    )
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "numba"), "PYTHONPATH": str(root),
           "PATH": "/usr/bin:/bin"}  # fmt: skip

    def run() -> str:
        out = subprocess.run(
            [sys.executable, "-c", script], env=env, capture_output=True, text=True,
            check=True, timeout=300,
        )  # fmt: skip
        where, what = out.stdout.split()
        assert where == str(root / "rangefuse" / "engine" / "__init__.py")  # the copy
        return what

    assert run() == "compiled"  # an empty cache
    assert run() == "loaded"  # the same sources: the build is used
    callee = root / "rangefuse" / "engine" / "certainty.py"  # grid.py is unchanged
    callee.write_text(callee.read_text() + "\n# changed\n")
    assert run() == "compiled"  # compiled again, not loaded
