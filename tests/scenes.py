"""Small analytic scenes and scans for the fusion tests (every sensor model).

Scans are small (tens of pixels a side) so that the dense reference of
``tests/reference.py`` runs in a fraction of a second.
"""

from __future__ import annotations

import math

import numpy as np
from rangefuse.engine import Scan, Sensor, sensor_from_dict
from rangefuse.engine.synth import AnalyticScene, SceneBuilder, render

#: Region of interest of the small scene, world metres.
BOUNDS = (-0.4, -0.4, -0.4, 0.4, 0.4, 0.4)


def small_scene() -> AnalyticScene:
    """A box, a sphere, a bar and a thin plate inside BOUNDS, with gaps to see through."""
    return (
        SceneBuilder()
        .add_box((0.05, -0.05, -0.1), (0.3, 0.25, 0.2), 0.4)
        .add_sphere((-0.15, 0.15, 0.12), 0.12)
        .add_cylinder((0.2, 0.2, -0.3), (0.2, 0.2, 0.25), 0.04)
        .add_box((-0.2, -0.2, 0.15), (0.02, 0.3, 0.25))
        .build()
    )


def pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def look_at_cv(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose of an OpenCV-frame sensor (x right, y down, z forward)."""
    eye = np.asarray(eye, np.float64)
    z = np.asarray(target, np.float64) - eye
    z /= np.linalg.norm(z)
    x = np.cross(z, up)
    if np.linalg.norm(x) < 1e-6:
        x = np.cross(z, (1.0, 0.0, 0.0))
    x /= np.linalg.norm(x)
    return pose(np.stack([x, np.cross(z, x), z], axis=1), eye)


def look_at_xfwd(eye, target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Pose of an x-forward, y-left, z-up sensor (spherical, cylindrical)."""
    eye = np.asarray(eye, np.float64)
    x = np.asarray(target, np.float64) - eye
    x /= np.linalg.norm(x)
    y = np.cross(up, x)
    y /= np.linalg.norm(y)
    return pose(np.stack([x, y, np.cross(x, y)], axis=1), eye)


SENSORS: dict[str, dict] = {
    "pinhole_ray": dict(
        model="pinhole",
        width=48,
        height=40,
        fx=45.0,
        fy=45.0,
        cx=23.5,
        cy=19.5,
        range_convention="ray",
        min_range=0.05,
        max_range=4.0,
    ),
    "pinhole_z": dict(
        model="pinhole",
        width=48,
        height=40,
        fx=45.0,
        fy=45.0,
        cx=23.5,
        cy=19.5,
        range_convention="z",
        min_range=0.05,
        max_range=4.0,
    ),
    "spherical": dict(
        model="spherical",
        width=180,
        height=24,
        az_min=-math.pi,
        az_max=math.pi,
        wrap=True,
        elevations=list(np.linspace(0.45, -0.6, 24) ** 3 * 2.0 + 0.0),
        max_range=3.0,
    ),
    "spherical_even": dict(
        model="spherical",
        width=120,
        height=20,
        az_min=-1.2,
        az_max=1.2,
        el_min=-0.5,
        el_max=0.5,
        max_range=3.0,
    ),
    "cylindrical": dict(
        model="cylindrical",
        width=160,
        height=30,
        az_min=-math.pi,
        az_max=math.pi,
        wrap=True,
        fy=20.0,
        cy=14.5,
        range_convention="ray",
        max_range=3.0,
    ),
    "linescan": dict(
        model="cylindrical",
        width=40,
        height=50,
        az_min=-0.35,
        az_max=0.35,
        fy=60.0,
        cy=24.5,
        axial="linear",
        range_convention="radial",
        max_range=3.0,
    ),
    "orthographic": dict(
        model="orthographic", width=40, height=40, sx=0.02, sy=0.02, cx=19.5, cy=19.5, max_range=3.0
    ),
}


def sensor(name: str) -> Sensor:
    return sensor_from_dict(SENSORS[name])


def poses(name: str, n: int) -> list[np.ndarray]:
    """``n`` poses of the named sensor around the small scene."""
    out = []
    for k in range(n):
        a = 2.0 * math.pi * k / n + 0.3
        h = 0.35 * math.sin(1.7 * k + 0.5)
        if name.startswith("pinhole"):
            out.append(look_at_cv((1.3 * math.cos(a), 1.3 * math.sin(a), h)))
        elif name == "orthographic":
            eye = np.array([1.5 * math.cos(a), 1.5 * math.sin(a), h])
            out.append(look_at_cv(eye))
        elif name in ("spherical", "cylindrical"):
            # inside a ring of the scene's own solids: put the sensor off centre, tilted
            R = look_at_xfwd((0, 0, 0), (math.cos(a), math.sin(a), 0.2 * math.sin(k)))[:3, :3]
            out.append(pose(R, np.array([0.55 * math.cos(a + 2.0), 0.55 * math.sin(a + 2.0), h])))
        else:  # sensors looking in from outside along x
            out.append(look_at_xfwd((1.2 * math.cos(a), 1.2 * math.sin(a), 0.1 * h)))
    return out


def scans(name: str, n: int, scene: AnalyticScene | None = None) -> list[tuple[str, Scan]]:
    scene = scene if scene is not None else small_scene()
    s = sensor(name)
    return [
        (f"{name}_{k:02d}", Scan(render(scene, s, T), T, s)) for k, T in enumerate(poses(name, n))
    ]
