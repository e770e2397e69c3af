"""numba's cache for the engine's kernels, keyed by every engine source file, not one.

numba keeps a compiled kernel with a stamp of the one file that defines it (a SHA-256 of its
text) and loads the build while that file is unchanged. But a kernel's machine code also
holds the kernels it calls from other files (compiled into it) and the globals it reads
(frozen at compilation): change only ``_sensor_kernels.py`` and ``fusion.py``'s kernels,
which call it, load their old builds, silently. A checkout updated with ``git pull`` (the
README's ``make run`` installs the repository in place) hits exactly that.

:func:`install` puts a locator in front of numba's own (``CacheImpl._locator_classes``) that
takes the engine's kernels (``engine/`` and its subpackages: the synthetic renderer's kernels
call the sensors'): the same cache folder numba would pick, and as the stamp a SHA-256 over
every ``.py`` file under ``engine/``. Any change to the engine makes every kernel
compile again on its next use; a change elsewhere (storage, the service) compiles nothing.
The kernels of the checkout's ``tests/`` (helpers that compile engine kernels into theirs)
are stamped with the engine's stamp and their own file's.
Importing this module installs it; ``engine/__init__.py`` imports it before any kernel is
defined (numba picks the locator when ``@njit(cache=True)`` decorates a function).
"""

from __future__ import annotations

import functools
import hashlib
from pathlib import Path
from typing import Any

__all__ = ["engine_source_stamp", "install", "source_stamp"]

ENGINE_DIR = Path(__file__).resolve().parent
#: The checkout's tests: their helper kernels compile the engine's in too, so their stamp
#: is the engine's and their own file's (absent where the package is installed alone).
TESTS_DIR = ENGINE_DIR.parent / "tests"


@functools.lru_cache(maxsize=1)
def engine_source_stamp() -> str:
    """The stamp of every kernel of the engine (:func:`source_stamp` of its folder)."""
    return source_stamp(ENGINE_DIR)


def source_stamp(folder: Path) -> str:
    """SHA-256 over the paths (relative to ``folder``) and texts of the ``.py`` files under
    ``folder``, in path order."""
    digest = hashlib.sha256()
    for path in sorted(folder.rglob("*.py")):
        text = path.read_bytes()
        digest.update(f"{path.relative_to(folder).as_posix()}\0{len(text)}\0".encode())
        digest.update(text)
    return "rangefuse-engine:" + digest.hexdigest()


class _EngineLocator:
    """The locator numba would use for a file under ``engine/``, with
    :func:`engine_source_stamp` as the stamp; ``from_function`` declines every other file
    (numba's own locators take it)."""

    #: numba's locators, in its order (set by :func:`install`).
    standard: tuple[Any, ...] = ()

    @classmethod
    def from_function(cls, py_func: Any, py_file: str) -> _EngineLocator | None:
        parents = Path(py_file).resolve().parents
        if ENGINE_DIR not in parents and TESTS_DIR not in parents:
            return None
        for locator_class in cls.standard:
            inner = locator_class.from_function(py_func, py_file)
            if inner is not None:
                return cls(inner, ENGINE_DIR not in parents)
        return None

    def __init__(self, inner: Any, own_file_too: bool = False) -> None:
        self._inner = inner
        self._own_file_too = own_file_too

    def get_source_stamp(self) -> Any:
        if self._own_file_too:  # a test's kernel: the engine's and its own file's
            return (engine_source_stamp(), self._inner.get_source_stamp())
        return engine_source_stamp()

    def __getattr__(self, name: str) -> Any:  # the cache path, the disambiguator, ...
        return getattr(self._inner, name)


def install() -> None:
    """Put :class:`_EngineLocator` first among numba's cache locators (once)."""
    from numba.core.caching import CacheImpl

    classes: list[Any] = CacheImpl._locator_classes
    if _EngineLocator not in classes:
        _EngineLocator.standard = tuple(classes)
        classes.insert(0, _EngineLocator)


install()
