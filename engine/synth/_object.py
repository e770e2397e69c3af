"""The ``object`` scene: a robot arm seen by a ray-range pinhole camera from all around.

A manipulator about 0.9 m across (base, column, upper arm, forearm, a gripper with two thin
fingers, and a rectangular handle on the column's back whose hole one can see through),
centred on the origin, seen from directions spread evenly over a 2 m sphere around it.
"""

from __future__ import annotations

import math

import numpy as np

from ..sensors import PinholeSensor
from ._builder import SceneBuilder, _fibonacci_sphere, _frame_along, _look_at
from ._scene import AnalyticScene

_OBJECT_VIEWS = 12
_OBJECT_CAMERA = PinholeSensor(
    width=640,
    height=480,
    fx=600.0,
    fy=600.0,
    cx=319.5,
    cy=239.5,
    range_convention="ray",
    min_range=0.1,
    max_range=6.0,
)
_OBJECT_ORBIT_RADIUS_M = 2.0
_OBJECT_BOUNDS_MARGIN_M = 0.05
# Robot manipulator, built with its base on z = 0 and then centred on the origin.
_BASE_RADIUS_M = 0.16
_BASE_HEIGHT_M = 0.06
_COLUMN_SIZE_M = (0.10, 0.10, 0.34)
_SHOULDER_RADIUS_M = 0.075
_UPPER_ARM_SECTION_M = (0.08, 0.07)
_ELBOW_RADIUS_M = 0.06
_FOREARM_RADIUS_M = 0.04
_WRIST_RADIUS_M = 0.045
_ARM_YAW = 0.35  # the arm's vertical plane, radians from +x
_ELBOW_IN_PLANE_M = (0.22, 0.66)  # (reach, height)
_WRIST_IN_PLANE_M = (0.50, 0.56)
_PALM_SIZE_M = (0.03, 0.12, 0.05)  # along the forearm, across, thickness
_FINGER_LENGTH_M = 0.09
_FINGER_THICKNESS_M = 0.012
_FINGER_HEIGHT_M = 0.03
_FINGER_GAP_M = 0.06
# A rectangular handle on the column's back: four bars around a see-through hole.
_HANDLE_REACH_M = 0.27  # from the column axis
_HANDLE_Z_M = (0.12, 0.34)
_HANDLE_BAR_M = 0.02
_HANDLE_DEPTH_M = 0.03


def _object_scene() -> AnalyticScene:
    b = SceneBuilder()
    b.add_cylinder((0.0, 0.0, 0.0), (0.0, 0.0, _BASE_HEIGHT_M), _BASE_RADIUS_M)
    column_top = _BASE_HEIGHT_M + _COLUMN_SIZE_M[2]
    b.add_box((0.0, 0.0, _BASE_HEIGHT_M + 0.5 * _COLUMN_SIZE_M[2]), _COLUMN_SIZE_M)
    shoulder = np.array([0.0, 0.0, column_top + 0.04])
    b.add_sphere(shoulder, _SHOULDER_RADIUS_M)
    plane = np.array([math.cos(_ARM_YAW), math.sin(_ARM_YAW), 0.0])
    elbow = plane * _ELBOW_IN_PLANE_M[0] + np.array([0.0, 0.0, _ELBOW_IN_PLANE_M[1]])
    wrist = plane * _WRIST_IN_PLANE_M[0] + np.array([0.0, 0.0, _WRIST_IN_PLANE_M[1]])
    b.add_bar(shoulder, elbow, *_UPPER_ARM_SECTION_M)
    b.add_sphere(elbow, _ELBOW_RADIUS_M)
    b.add_cylinder(elbow, wrist, _FOREARM_RADIUS_M)
    b.add_sphere(wrist, _WRIST_RADIUS_M)
    # Gripper: palm across the forearm's end, two thin fingers with a gap between them.
    R = _frame_along(wrist - elbow)  # x along the forearm, y across (horizontal), z ~ up
    along, across = R[:, 0], R[:, 1]
    palm = wrist + along * (_WRIST_RADIUS_M + 0.5 * _PALM_SIZE_M[0])
    b.add_box(palm, _PALM_SIZE_M, R)
    finger_offset = 0.5 * (_FINGER_GAP_M + _FINGER_THICKNESS_M)
    finger_centre = palm + along * 0.5 * (_PALM_SIZE_M[0] + _FINGER_LENGTH_M)
    finger_size = (_FINGER_LENGTH_M, _FINGER_THICKNESS_M, _FINGER_HEIGHT_M)
    for side in (-1.0, 1.0):
        b.add_box(finger_centre + side * finger_offset * across, finger_size, R)
    # Handle on the side away from the arm.
    back = -plane
    inner = 0.5 * _COLUMN_SIZE_M[0]
    z0, z1 = _HANDLE_Z_M
    bar, depth = _HANDLE_BAR_M, _HANDLE_DEPTH_M
    r_mid = 0.5 * (inner + _HANDLE_REACH_M)
    length = _HANDLE_REACH_M - inner
    yaw = _ARM_YAW + math.pi
    for z in (z0 + 0.5 * bar, z1 - 0.5 * bar):  # top and bottom bars
        b.add_box(back * r_mid + (0.0, 0.0, z), (length, depth, bar), yaw)
    for r in (inner + 0.5 * bar, _HANDLE_REACH_M - 0.5 * bar):  # the two uprights
        b.add_box(back * r + (0.0, 0.0, 0.5 * (z0 + z1)), (bar, depth, z1 - z0), yaw)
    bounds = np.array(b.build().bounds())
    return b.build(offset=-0.5 * (bounds[:3] + bounds[3:]))


def _object_poses(views: int, scene: AnalyticScene) -> list[np.ndarray]:
    bounds = np.array(scene.bounds())
    centre = 0.5 * (bounds[:3] + bounds[3:])
    directions = _fibonacci_sphere(views)
    return [_look_at(centre + _OBJECT_ORBIT_RADIUS_M * d, centre) for d in directions]
