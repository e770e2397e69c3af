"""The ``room`` scene: a furnished room seen by a z-depth RGB-D camera on a closed loop.

A 5 x 4 x 2.6 m room with a window and a door recessed in its walls, a table with two chairs
on a rug, a shelf, a sofa, a rotated cabinet, a ball and a floor lamp; the camera moves on an
ellipse around the room's centre, looking across the room.
"""

from __future__ import annotations

import math

import numpy as np

from ..sensors import PinholeSensor
from ._builder import SceneBuilder, _rotation_z, _yaw_pitch_camera
from ._scene import AnalyticScene

_ROOM_VIEWS = 100
_ROOM_CAMERA = PinholeSensor(
    width=640,
    height=480,
    fx=525.0,
    fy=525.0,
    cx=319.5,
    cy=239.5,
    range_convention="z",
    min_range=0.1,
    max_range=8.0,
)
_ROOM_BOUNDS_MARGIN_M = 0.1
_ROOM_SIZE_M = (5.0, 4.0, 2.6)  # interior x, y, z; the floor is z = 0, the room centred on x, y
_WALL_M = 0.1  # thickness of floor, ceiling and walls, all outside the interior
_WINDOW_X_M = (-0.7, 0.7)  # in the +y wall
_WINDOW_Z_M = (0.9, 1.9)
_DOOR_Y_M = (-0.45, 0.45)  # in the +x wall
_DOOR_HEIGHT_M = 2.05
_PANE_M = 0.08  # thickness of the window pane and the door, set behind the wall (recessed)
# Camera loop: an ellipse around the room centre, looking across the room.
_LOOP_RADII_M = (1.25, 0.8)
_LOOP_HEIGHT_M = 1.5
_LOOP_HEIGHT_SWING_M = 0.15
_LOOP_YAW_SWING = 0.6  # radians either side of looking at the opposite side
_LOOP_PITCH = -0.32  # radians, mean
_LOOP_PITCH_SWING = 0.3


def _room_shell(b: SceneBuilder) -> None:
    sx, sy, sz = _ROOM_SIZE_M
    hx, hy, w = 0.5 * sx, 0.5 * sy, _WALL_M
    full_x, full_y, full_z = sx + 2 * w, sy + 2 * w, sz + 2 * w
    b.add_box((0.0, 0.0, -0.5 * w), (full_x, full_y, w))  # floor
    b.add_box((0.0, 0.0, sz + 0.5 * w), (full_x, full_y, w))  # ceiling
    b.add_box((-hx - 0.5 * w, 0.0, 0.5 * sz), (w, full_y, full_z))  # -x wall
    b.add_box((0.0, -hy - 0.5 * w, 0.5 * sz), (full_x, w, full_z))  # -y wall
    # +y wall around a window opening; the pane is recessed behind it.
    (wx0, wx1), (wz0, wz1) = _WINDOW_X_M, _WINDOW_Z_M
    y_wall = hy + 0.5 * w
    left, right = wx0 - (-hx - w), (hx + w) - wx1
    b.add_box((-hx - w + 0.5 * left, y_wall, 0.5 * sz), (left, w, full_z))
    b.add_box((wx1 + 0.5 * right, y_wall, 0.5 * sz), (right, w, full_z))
    b.add_box((0.5 * (wx0 + wx1), y_wall, 0.5 * (wz0 - w)), (wx1 - wx0, w, wz0 + w))
    b.add_box((0.5 * (wx0 + wx1), y_wall, 0.5 * (wz1 + sz + w)), (wx1 - wx0, w, sz + w - wz1))
    b.add_box(
        (0.0, hy + w + 0.5 * _PANE_M, 0.5 * (wz0 + wz1)),
        (wx1 - wx0 + 0.2, _PANE_M, wz1 - wz0 + 0.2),
    )
    # +x wall around a door opening; the door is recessed behind it.
    (dy0, dy1), dz = _DOOR_Y_M, _DOOR_HEIGHT_M
    x_wall = hx + 0.5 * w
    front, rear = dy0 - (-hy - w), (hy + w) - dy1
    b.add_box((x_wall, -hy - w + 0.5 * front, 0.5 * sz), (w, front, full_z))
    b.add_box((x_wall, dy1 + 0.5 * rear, 0.5 * sz), (w, rear, full_z))
    b.add_box((x_wall, 0.5 * (dy0 + dy1), 0.5 * (dz + sz + w)), (w, dy1 - dy0, sz + w - dz))
    b.add_box(
        (hx + w + 0.5 * _PANE_M, 0.5 * (dy0 + dy1), 0.5 * dz), (_PANE_M, dy1 - dy0 + 0.2, dz + 0.2)
    )


def _table(b: SceneBuilder, x: float, y: float, size: tuple[float, float], height: float) -> None:
    top, leg = 0.04, 0.05
    b.add_box((x, y, height - 0.5 * top), (size[0], size[1], top))
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            lx = x + sx * (0.5 * size[0] - 0.06)
            ly = y + sy * (0.5 * size[1] - 0.06)
            b.add_box((lx, ly, 0.5 * (height - top)), (leg, leg, height - top))


def _chair(b: SceneBuilder, x: float, y: float, yaw: float) -> None:
    seat, seat_h, back_h, thick, leg_r = 0.44, 0.45, 0.45, 0.04, 0.018
    R = _rotation_z(yaw)
    b.add_box((x, y, seat_h - 0.5 * thick), (seat, seat, thick), yaw)
    for sx in (-1.0, 1.0):
        for sy in (-1.0, 1.0):
            p = np.array([x, y, 0.0]) + R @ np.array([sx * 0.19, sy * 0.19, 0.0])
            b.add_cylinder(p, p + np.array([0.0, 0.0, seat_h - thick]), leg_r)
    back = np.array([x, y, seat_h + 0.5 * back_h]) + R @ np.array([-0.5 * seat + 0.02, 0, 0])
    b.add_box(back, (thick, seat, back_h), yaw)


def _room_scene() -> AnalyticScene:
    b = SceneBuilder()
    _room_shell(b)
    hx, hy = 0.5 * _ROOM_SIZE_M[0], 0.5 * _ROOM_SIZE_M[1]
    # Table with two chairs, a thin rug under them.
    b.add_box((0.4, -0.1, 0.005), (2.0, 1.4, 0.01))
    _table(b, 0.4, -0.1, (1.2, 0.8), 0.76)
    _chair(b, -0.45, -0.1, 0.0)
    _chair(b, 0.4, 0.65, -0.5 * math.pi)
    # Shelf against the -x wall: two sides, a back and four boards.
    depth, width, height, board = 0.35, 1.0, 1.8, 0.02
    x0, yc = -hx, 0.6
    xc = x0 + 0.5 * depth
    for s in (-1.0, 1.0):
        b.add_box((xc, yc + s * (0.5 * width - 0.5 * board), 0.5 * height), (depth, board, height))
    b.add_box((x0 + 0.5 * board, yc, 0.5 * height), (board, width, height))
    for z in (0.05, 0.6, 1.2, height - 0.5 * board):
        b.add_box((xc, yc, z), (depth, width - 2 * board, board))
    # Sofa against the -y wall: seat block, back rest, two arm rests.
    sofa_x, sofa_w, sofa_d = -0.7, 2.0, 0.85
    b.add_box((sofa_x, -hy + 0.5 * sofa_d, 0.21), (sofa_w, sofa_d, 0.42))
    b.add_box((sofa_x, -hy + 0.1, 0.62), (sofa_w, 0.2, 0.4))
    for s in (-1.0, 1.0):
        b.add_box(
            (sofa_x + s * (0.5 * sofa_w - 0.1), -hy + 0.5 * sofa_d, 0.53), (0.2, sofa_d, 0.22)
        )
    # A low cabinet by the door, rotated, with a ball next to it.
    b.add_box((1.9, -1.45, 0.3), (0.8, 0.45, 0.6), 0.4)
    b.add_sphere((1.55, 0.9, 0.12), 0.12)
    # Floor lamp in a corner: base, pole, spherical shade.
    lamp = (hx - 0.35, hy - 0.35)
    b.add_cylinder((*lamp, 0.0), (*lamp, 0.03), 0.15)
    b.add_cylinder((*lamp, 0.03), (*lamp, 1.55), 0.015)
    b.add_sphere((*lamp, 1.6), 0.18)
    return b.build()


def _room_poses(views: int) -> list[np.ndarray]:
    poses = []
    for k in range(views):
        angle = 2.0 * math.pi * k / views
        position = np.array(
            [
                _LOOP_RADII_M[0] * math.cos(angle),
                _LOOP_RADII_M[1] * math.sin(angle),
                _LOOP_HEIGHT_M + _LOOP_HEIGHT_SWING_M * math.sin(2.0 * angle),
            ]
        )
        yaw = angle + math.pi + _LOOP_YAW_SWING * math.sin(3.0 * angle)
        pitch = _LOOP_PITCH + _LOOP_PITCH_SWING * math.sin(5.0 * angle)
        poses.append(_yaw_pitch_camera(position, yaw, pitch))
    return poses
