"""Poses as foreign files write them: quaternions, 3x4 and 4x4 matrices in text.

Real pose files round their numbers (six digits are common), so their rotations are
slightly non-orthonormal; :func:`snap_rotation` replaces such a rotation by the nearest
true rotation (the orthogonal factor of its SVD, Higham 1988), notes the correction in a
:class:`PoseFixes` (one warning per file) when it is larger than the engine would accept
silently, and refuses rotations that are grossly wrong (a scale, a shear, a reflection),
naming the file and line.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import SourceError

__all__ = [
    "QUATERNION_REFUSE",
    "QUATERNION_SILENT",
    "ROTATION_REFUSE",
    "ROTATION_SILENT",
    "PoseFixes",
    "numeric_lines",
    "parse_floats",
    "pose_from_quaternion",
    "rigid_pose",
    "snap_rotation",
]

#: ``max |R^T R - I|`` up to which a rotation is orthonormalised without a word: the
#: tolerance of :func:`engine.check_pose` (7-digit files, as KITTI's and 7-Scenes', stay
#: below it).
ROTATION_SILENT = 1e-5
#: ``max |R^T R - I|`` above which a rotation is refused: a 1 % scale or shear is a wrong
#: file, not rounding.
ROTATION_REFUSE = 1e-2
#: ``| |q| - 1 |`` up to which a quaternion is normalised without a word: TUM prints four
#: decimals, which leaves the norm up to 2e-4 off.
QUATERNION_SILENT = 1e-3
#: ``| |q| - 1 |`` above which a quaternion is refused.
QUATERNION_REFUSE = 1e-2


@dataclass
class PoseFixes:
    """What the readers corrected in pose files: one warning per file and kind of fix, with
    the count and the largest correction (a long trajectory gives one line, not thousands)."""

    _fixes: dict[tuple[str, str], list[tuple[int, float]]] = field(default_factory=dict)

    def note(self, path: Path | str, line: int, what: str, deviation: float) -> None:
        self._fixes.setdefault((str(path), what), []).append((line, deviation))

    def warnings(self) -> list[str]:
        out = []
        for (path, what), fixes in self._fixes.items():
            line, worst = max(fixes, key=lambda fix: fix[1])
            out.append(f"{path}: {len(fixes)} {what} (largest deviation {worst:.2g}, line {line})")
        return out


def snap_rotation(R: np.ndarray, path: Path | str, line: int, fixes: PoseFixes) -> np.ndarray:
    """The rotation nearest to ``R`` (Frobenius norm).

    Parameters
    ----------
    R : array (3, 3)
    path, line : the file and line it comes from, for the messages
    fixes : PoseFixes
        Notes the correction when ``max |R^T R - I|`` exceeds :data:`ROTATION_SILENT`.

    Raises
    ------
    SourceError
        When the deviation exceeds :data:`ROTATION_REFUSE` or ``det R < 0`` (a reflection).
    """
    R = np.asarray(R, np.float64)
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_REFUSE:
        raise SourceError(
            f"{path} line {line}: not a rotation (max |R^T R - I| = {err:.3g}, more than "
            f"{ROTATION_REFUSE:g}: a scale, shear or a wrong matrix layout)"
        )
    if np.linalg.det(R) <= 0.0:
        raise SourceError(f"{path} line {line}: a reflection (det R < 0), not a rotation")
    U, _, Vt = np.linalg.svd(R)
    if err > ROTATION_SILENT:
        fixes.note(
            path,
            line,
            "rotations not orthonormal, snapped to the nearest rotation (max |R^T R - I|)",
            err,
        )
    return U @ Vt


def rigid_pose(M: np.ndarray, path: Path | str, line: int, fixes: PoseFixes) -> np.ndarray:
    """A 4x4 rigid pose from a 3x4 or 4x4 matrix, its rotation snapped (:func:`snap_rotation`).

    Raises
    ------
    SourceError
        For non-finite entries, a last row other than ``0 0 0 1``, or a rotation that
        :func:`snap_rotation` refuses.
    """
    M = np.asarray(M, np.float64)
    if not np.all(np.isfinite(M)):
        raise SourceError(f"{path} line {line}: pose has non-finite entries")
    if M.shape == (4, 4):
        if not np.allclose(M[3], [0.0, 0.0, 0.0, 1.0], atol=1e-6):
            raise SourceError(
                f"{path} line {line}: last row of a 4x4 pose must be 0 0 0 1, got {M[3]}"
            )
    elif M.shape != (3, 4):
        raise SourceError(f"{path} line {line}: a pose must be 3x4 or 4x4, got {M.shape}")
    T = np.eye(4)
    T[:3, :3] = snap_rotation(M[:3, :3], path, line, fixes)
    T[:3, 3] = M[:3, 3]
    return T


def pose_from_quaternion(
    t: np.ndarray, q_xyzw: np.ndarray, path: Path | str, line: int, fixes: PoseFixes
) -> np.ndarray:
    """4x4 pose ``[[R(q), t], [0, 0, 0, 1]]`` from a translation and a scalar-last quaternion.

    ``R(q)`` is the rotation of the Hamilton unit quaternion ``qw + qx i + qy j + qz k``.
    The quaternion is normalised; a norm off by more than :data:`QUATERNION_SILENT` is
    noted in ``fixes``, by more than :data:`QUATERNION_REFUSE` refused.
    """
    q = np.asarray(q_xyzw, np.float64)
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or not np.all(np.isfinite(t)):
        raise SourceError(f"{path} line {line}: pose has non-finite entries")
    if abs(norm - 1.0) > QUATERNION_REFUSE:
        raise SourceError(
            f"{path} line {line}: quaternion (qx qy qz qw) has norm {norm:.6g}, not 1: "
            "not a rotation"
        )
    if abs(norm - 1.0) > QUATERNION_SILENT:
        fixes.note(
            path, line, "quaternions not of unit norm, normalised (| |q| - 1 |)", abs(norm - 1.0)
        )
    x, y, z, w = q / norm
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def numeric_lines(path: Path, comment: str = "#") -> Iterator[tuple[int, list[str]]]:
    """``(line_number, tokens)`` of the non-empty, non-comment lines of a text file.

    Raises
    ------
    SourceError
        When the file cannot be read as text.
    """
    try:
        text = path.read_text(encoding="utf-8", errors="strict")
    except FileNotFoundError:
        raise SourceError(f"{path}: no such file") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise SourceError(f"{path}: cannot be read as text ({exc})") from None
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith(comment):
            continue
        yield number, stripped.replace(",", " ").split()


def parse_floats(tokens: list[str], where: str, expected: int | None, what: str) -> np.ndarray:
    """The tokens as float64; refuses a wrong count or a non-number, naming ``where``."""
    if expected is not None and len(tokens) != expected:
        raise SourceError(f"{where}: expected {expected} numbers ({what}), got {len(tokens)}")
    try:
        return np.array([float(tok) for tok in tokens], np.float64)
    except ValueError:
        bad = next(tok for tok in tokens if not _is_float(tok))
        raise SourceError(f"{where}: {bad!r} is not a number ({what})") from None


def _is_float(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True
