"""Synthetic range data: analytic scenes rendered into range maps.

An :class:`AnalyticScene` is a union of convex solids (oriented boxes, spheres and capped
cylinders) with exact ray casting and exact signed distances, so that tests and benchmarks
know the true surface of everything they fuse. :class:`SceneBuilder` assembles one.
:func:`render` turns a scene, a sensor and a pose ``T_W_S`` into the range map the sensor
would measure, in the dataset encoding of ``docs/formats.md`` (``+inf``: no return within
``max_range``, NaN: closer than ``min_range``); :func:`apply_noise` adds range noise, spikes,
dropouts and an invalid background (:class:`NoiseSpec`, :func:`parse_noise`);
:func:`make_dataset` builds the three scenes of ``rangefuse synth`` (``object``, ``room``,
``street``) with their sensors and poses.

The private modules, from the bottom up:

- ``_solids``: the rows that describe solids, their ray intervals and signed distances;
- ``_hierarchy``: the bounding-volume hierarchy and the kernels that walk it;
- ``_scene``: :class:`AnalyticScene`, the API over those kernels;
- ``_render``: :func:`render` and its kernel;
- ``_noise``: :class:`NoiseSpec`, :func:`parse_noise`, :func:`apply_noise`;
- ``_builder``: :class:`SceneBuilder` and the pose helpers;
- ``_object``, ``_room``, ``_street``: the three scenes with their sensors and poses;
- ``_datasets``: :class:`SyntheticDataset` and :func:`make_dataset`.

Geometry and poses are deterministic; only the noise depends on the seed.
"""

from ._builder import SceneBuilder
from ._datasets import SCENES, SyntheticDataset, make_dataset
from ._noise import NoiseSpec, apply_noise, parse_noise
from ._render import render
from ._scene import AnalyticScene

__all__ = [
    "SCENES",
    "AnalyticScene",
    "NoiseSpec",
    "SceneBuilder",
    "SyntheticDataset",
    "apply_noise",
    "make_dataset",
    "parse_noise",
    "render",
]
