"""``rangefuse warmup``: compile every kernel into numba's cache ahead of time; the note
that the command line prints when a kernel is compiled (:func:`announce_compilation`); and
what the cache holds (:func:`cache_state`, :func:`cache_note`: ``rangefuse serve`` and each
worker say at start whether the first jobs will compile).

Fuses and meshes tiny renderings of a small analytic scene with every sensor model, both
certainty shapes, the filters and the discontinuity test, in mapping and closed mode, so
that the first real job does not spend a minute compiling (the Docker image runs it at
build time). The kernels land in ``NUMBA_CACHE_DIR`` (see :mod:`rangefuse.service`).
"""

from __future__ import annotations

import argparse
import math
import pickle
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from . import numba_cache_dir
from ._progress import note

if TYPE_CHECKING:
    import numpy as np

__all__ = [
    "COMPILING",
    "CacheState",
    "add_warmup_command",
    "announce_compilation",
    "cache_note",
    "cache_state",
    "warm_kernels",
]

#: What the command line prints when numba compiles a kernel that its cache does not hold.
COMPILING = "compiling kernels, first run only"


def announce_compilation() -> None:
    """Print a note on standard error the first time this process compiles a kernel: numba
    compiles one only when its cache (``NUMBA_CACHE_DIR``) holds no build of it for these
    argument types, so a cold cache is seen exactly when it costs time. Loading from the
    cache prints nothing."""
    global _listening
    if _listening:
        return
    from numba.core import event

    class _Compiling(event.Listener):
        def on_start(self, ev: Any) -> None:
            global _listening
            event.unregister("numba:compile", self)  # once
            _listening = False
            note(
                f"{COMPILING} (up to a few minutes; cached in {numba_cache_dir()}; "
                "`rangefuse warmup` compiles them all ahead of time)"
            )

        def on_end(self, ev: Any) -> None:
            pass

    event.register("numba:compile", _Compiling())
    _listening = True


#: Whether :func:`announce_compilation` waits for a compilation to announce.
_listening = False


@dataclass(frozen=True)
class CacheState:
    """What numba's cache holds of the engine's kernels (the ones jobs run): ``fresh``
    kernels built from the engine's current source, ``stale`` ones built from an older
    source or by another numba (compiled again on first use)."""

    path: Path
    fresh: int
    stale: int

    @property
    def cold(self) -> bool:
        """No kernel of this engine is cached: the first job compiles every one it needs."""
        return self.fresh == 0


def cache_state() -> CacheState:
    """Read the index files of the engine's kernels in numba's cache (``NUMBA_CACHE_DIR``,
    which :mod:`rangefuse.service` sets): one per kernel and line where it starts
    (``fusion._integrate_kernel.locals.integrate-83.py311.nbi``), holding numba's version
    and the stamp of the engine's sources (``engine._numba_cache``), which numba compares
    before loading a build. A
    kernel counts as fresh when one of its index files is; the index of a function that no
    longer exists is left out."""
    import numba
    import rangefuse.engine
    from numba.core.caching import _CacheLocator
    from rangefuse.engine._numba_cache import engine_source_stamp

    engine_dir = Path(rangefuse.engine.__file__).resolve().parent
    folder = numba_cache_dir() / _CacheLocator.get_suitable_cache_subpath(
        str(engine_dir / "__init__.py")
    )
    sources: dict[str, str] = {}  # module -> its text
    stamp_now = engine_source_stamp()
    kernels: dict[str, bool] = {}  # module.qualname -> whether a fresh build is cached
    for index in sorted(folder.glob("*.nbi")):
        kernel = index.name.rsplit("-", 1)[0]
        module, _, qualname = kernel.partition(".")
        source = engine_dir / f"{module}.py"
        if not source.is_file():  # a module that is gone
            continue
        if module not in sources:
            sources[module] = source.read_text()
        if f"def {qualname.rsplit('.', 1)[-1]}(" not in sources[module]:  # a function gone
            continue
        try:
            with open(index, "rb") as fh:
                version = pickle.load(fh)
                stamp, overloads = pickle.loads(fh.read())
            fresh = version == numba.__version__ and stamp == stamp_now and bool(overloads)
        except Exception:  # unreadable: numba compiles again
            fresh = False
        kernels[kernel] = kernels.get(kernel, False) or fresh
    n_fresh = sum(kernels.values())
    return CacheState(numba_cache_dir(), n_fresh, len(kernels) - n_fresh)


def cache_note() -> str:
    """One line on what the cache holds for the service's log: cold, partly out of date, or
    warm."""
    try:
        state = cache_state()
    except Exception as exc:  # numba's cache layout changed: say so, never stop the service
        return f"could not read numba's cache {numba_cache_dir()} ({type(exc).__name__}: {exc})"
    warmup = "`rangefuse warmup` compiles them all ahead of time"
    if state.cold:
        return (
            f"numba's cache {state.path} holds no compiled kernel of this rangefuse: the first "
            f"jobs compile the kernels they need (up to 2 minutes; jobs say 'compiling kernels' "
            f"meanwhile); {warmup}"
        )
    if state.stale:
        return (
            f"numba's cache {state.path} holds {state.fresh} compiled kernels of this rangefuse "
            f"and {state.stale} out of date: jobs that need those compile them first; {warmup}"
        )
    return f"numba's cache {state.path} holds {state.fresh} compiled kernels of this rangefuse"


_BOUNDS = (-0.4, -0.4, -0.4, 0.4, 0.4, 0.4)
#: One small sensor per model and range convention, and where it looks from.
_SENSORS = {
    "pinhole z": (
        {"model": "pinhole", "width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "cx": 15.5,
         "cy": 11.5, "range_convention": "z", "max_range": 4.0},
        "cv",
    ),
    "pinhole ray": (
        {"model": "pinhole", "width": 32, "height": 24, "fx": 30.0, "fy": 30.0, "cx": 15.5,
         "cy": 11.5, "range_convention": "ray", "max_range": 4.0},
        "cv",
    ),
    "spherical": (
        {"model": "spherical", "width": 90, "height": 12, "az_min": -math.pi, "az_max": math.pi,
         "wrap": True, "elevations": [0.5 - k / 11 for k in range(12)], "max_range": 3.0},
        "xfwd",
    ),
    "spherical, even rows": (
        {"model": "spherical", "width": 60, "height": 10, "az_min": -1.2, "az_max": 1.2,
         "el_min": -0.5, "el_max": 0.5, "max_range": 3.0},
        "xfwd",
    ),
    "cylindrical": (
        {"model": "cylindrical", "width": 80, "height": 16, "az_min": -math.pi,
         "az_max": math.pi, "wrap": True, "fy": 20.0, "cy": 7.5, "range_convention": "ray",
         "max_range": 3.0},
        "xfwd",
    ),
    "line scan": (
        {"model": "cylindrical", "width": 20, "height": 24, "az_min": -0.35, "az_max": 0.35,
         "fy": 30.0, "cy": 11.5, "axial": "linear", "range_convention": "radial",
         "max_range": 3.0},
        "xfwd",
    ),
    "orthographic": (
        {"model": "orthographic", "width": 24, "height": 24, "sx": 0.035, "sy": 0.035,
         "cx": 11.5, "cy": 11.5, "max_range": 4.0},
        "cv",
    ),
}  # fmt: skip


def _pose(eye: np.ndarray, frame: str) -> np.ndarray:
    """Looking at the origin from ``eye``: OpenCV axes (``cv``) or x forward (``xfwd``)."""
    import numpy as np

    forward = -eye / np.linalg.norm(eye)
    side = np.cross(forward, (0.0, 0.0, 1.0))
    side /= np.linalg.norm(side)
    T = np.eye(4)
    if frame == "cv":  # x right, y down, z forward
        T[:3, :3] = np.stack([side, np.cross(forward, side), forward], axis=1)
    else:  # x forward, y left, z up
        left = -side
        T[:3, :3] = np.stack([forward, left, np.cross(forward, left)], axis=1)
    T[:3, 3] = eye
    return T


def warm_kernels() -> int:
    """Compile (or load) every kernel; returns how many fusions it ran."""
    import numpy as np
    from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Scan, Volume, sensor_from_dict
    from rangefuse.engine.synth import SceneBuilder, render

    scene = (
        SceneBuilder()
        .add_box((0.05, -0.05, -0.1), (0.3, 0.25, 0.2), 0.4)
        .add_sphere((-0.15, 0.15, 0.12), 0.12)
        .build()
    )
    eyes = [np.array(e, np.float64) for e in ((1.2, 0.3, 0.4), (-0.9, 0.8, -0.3))]
    runs = 0
    for sensor_dict, frame in _SENSORS.values():
        sensor = sensor_from_dict(sensor_dict)
        scans = []
        for n, eye in enumerate(eyes):
            T = _pose(eye, frame)
            scans.append((f"s{n}", Scan(render(scene, sensor, T), T, sensor)))
        for shape, filt, disc in (("linear", "none", None), ("erf", "median3", 0.05),
                                  ("linear", "mean5", None)):  # fmt: skip
            params = FusionParams(NoiseModel(eps=0.04, rho=0.05, shape=shape), filter=filt,
                                  max_discontinuity=disc)  # fmt: skip
            for mode in ("mapping", "closed"):
                volume = Volume(GridSpec(0.02, 8, mode, _BOUNDS), params)
                volume.add_many(scans)
                volume.extract_mesh(refine=True)
                volume.remove("s0")
                runs += 1
    return runs


def _cmd_warmup(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    runs = warm_kernels()
    print(f"compiled the kernels ({runs} fusions) into {numba_cache_dir()} in "
          f"{time.perf_counter() - t0:.1f} s")  # fmt: skip
    return 0


def add_warmup_command(warmup: argparse.ArgumentParser) -> None:
    """The arguments of ``warmup`` (none)."""
    warmup.set_defaults(func=_cmd_warmup)
