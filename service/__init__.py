"""rangefuse service: the REST service, jobs and the runners that carry out their units of
work, the command line.

Importing it points numba's cache at one folder per machine, unless ``NUMBA_CACHE_DIR`` is
set: ``$XDG_CACHE_HOME/rangefuse/numba`` (``~/.cache/rangefuse/numba``). The command line,
the service and the cluster's workers all import this package before the engine, so each
kernel is compiled once per machine, not once per process or per way of starting
(``docs/scale-out.md``; ``rangefuse warmup`` compiles them all ahead of time).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["numba_cache_dir"]


def numba_cache_dir() -> Path:
    """Where numba keeps compiled kernels for the command line, the service and workers."""
    configured = os.environ.get("NUMBA_CACHE_DIR")
    if configured:
        return Path(configured)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rangefuse" / "numba"


os.environ.setdefault("NUMBA_CACHE_DIR", str(numba_cache_dir()))
