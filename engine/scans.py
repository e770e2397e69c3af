"""Scans, fusion parameters, and scans prepared for the kernels.

A :class:`Scan` is one registered range map (FORMAT.md): an H x W float32
array of ranges (finite: a measurement, ``+inf``: no return, NaN: invalid), a
sensor model, a pose ``T_W_S`` (sensor-to-world) and optional noise overrides.
Constructing one validates everything; the message of the error names the field. A finite
range beyond the sensor's ``max_range`` is not a surface: it becomes NaN (invalid) and is
counted (``Scan.far_ranges``); a map whose measured ranges mostly lie there, or look like
millimetres, is refused (:class:`FarRangesError`) unless accepted explicitly
(:func:`check_far_ranges`, ``docs/input-safety.md``).

:func:`prepare_scan` applies the scene's :class:`FusionParams` once (filter,
no-return policy) and computes what the kernels need: the prepared range map,
the pose as ``p_S = M x_W + c``, and the quad-block maps of the tile tests.
"""

from __future__ import annotations

from dataclasses import InitVar, dataclass, field
from typing import Any

import numpy as np

from . import _sampling
from ._memory import Scratch
from .certainty import NoiseModel
from .errors import FarRangesError, InvalidInputError, InvalidScanError
from .filters import filter_range
from .params import PARAMS, current_names, params_of
from .sensors import Sensor

__all__ = [
    "NO_RETURN",
    "FusionParams",
    "PreparedScan",
    "Scan",
    "check_far_ranges",
    "check_pose",
    "check_range_layout",
    "prepare_scan",
]

NO_RETURN = PARAMS["no_return"].choices
#: Largest deviation of ``R^T R`` from the identity accepted in a pose.
_ROTATION_TOLERANCE = 1e-5
#: A range map is refused when more than this share of its measured ranges lie beyond the
#: sensor's ``max_range`` ...
FAR_SHARE_LIMIT = 0.5
#: ... or when at least this share of them are whole numbers and their median is over
#: MILLIMETRE_MEDIAN_M: depth in millimetres (or centimetres) read as metres, which a
#: generous ``max_range`` lets through.
WHOLE_SHARE_LIMIT = 0.9
MILLIMETRE_MEDIAN_M = 100.0
#: The median and the share of whole numbers are taken over at most this many ranges.
_SAMPLE = 1 << 16


def check_pose(T_W_S: Any, field_name: str = "pose") -> np.ndarray:
    """Validate a 4x4 rigid sensor-to-world transform; returns it as float64."""
    try:
        T = np.array(T_W_S, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidScanError(field_name, "must be a 4x4 array of numbers") from None
    if T.shape != (4, 4):
        raise InvalidScanError(field_name, f"must be 4x4, got shape {T.shape}")
    if not np.all(np.isfinite(T)):
        raise InvalidScanError(field_name, "has non-finite entries (NaN or inf)")
    if not np.array_equal(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise InvalidScanError(field_name, f"last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    R = T[:3, :3]
    with np.errstate(over="ignore", invalid="ignore"):  # huge entries: err is inf
        err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > _ROTATION_TOLERANCE:
        raise InvalidScanError(
            field_name,
            f"is not rigid: its rotation is not orthonormal (max |R^T R - I| = {err:.3g}, "
            f"tolerance {_ROTATION_TOLERANCE:g})",
        )
    if np.linalg.det(R) < 0.0:
        raise InvalidScanError(field_name, "is a reflection (det R = -1), not a rotation")
    return T


def check_range_layout(
    dtype: np.dtype, shape: tuple[int, ...], sensor_shape: tuple[int, int] | None = None
) -> None:
    """Check a range map's dtype and shape (and that it fits a sensor of ``sensor_shape``)
    before its data exist: a file's header is checked with the words :class:`Scan` uses."""
    if dtype.kind != "f":
        raise InvalidScanError(
            "range",
            f"must be a floating-point array of metres, got dtype {dtype} "
            "(convert depth units to metres; invalid pixels are NaN)",
        )
    if len(shape) != 2:
        raise InvalidScanError("range", f"must be a 2-D array (H x W), got shape {tuple(shape)}")
    if sensor_shape is not None and tuple(shape) != tuple(sensor_shape):
        raise InvalidScanError(
            "range",
            f"shape {tuple(shape)} does not match the sensor's height x width "
            f"{tuple(sensor_shape)}",
        )


def _metres(value: float) -> str:
    return f"{value:,.0f} m" if abs(value) >= 1000.0 else f"{value:.4g} m"


def _measured_sample(range_m: np.ndarray, measured: int) -> np.ndarray:
    """Up to about _SAMPLE of the finite ranges, taken at a fixed stride (float64)."""
    flat = range_m.reshape(-1)
    sample = flat[:: max(1, flat.size // _SAMPLE)]
    sample = sample[np.isfinite(sample)]
    if len(sample) < min(measured, 1000):  # sparse maps: the stride missed most of them
        sample = flat[np.isfinite(flat)]
    return sample.astype(np.float64)


def check_far_ranges(
    range_m: np.ndarray, max_range_m: float, accept: bool = False
) -> tuple[np.ndarray, int]:
    """Find the finite ranges beyond ``max_range_m`` and check that the map is in metres.

    A finite range beyond the sensor's ``max_range`` is not a surface (the sensor cannot
    measure it): :class:`Scan` sets those pixels to NaN. When most of the measured ranges lie
    there, or they look like millimetres, the map is refused (docs/input-safety.md).

    Parameters
    ----------
    range_m : array (H, W), float
        Ranges in metres; ``+inf`` (no return) and NaN (invalid) are not measured ranges.
    max_range_m : float
        The sensor's ``max_range``.
    accept : bool
        Fuse the map anyway: no :class:`FarRangesError` (the far pixels are still found).

    Returns
    -------
    far : array (H, W), bool
        The finite ranges beyond ``max_range_m``.
    count : int
        How many there are.

    Raises
    ------
    FarRangesError
        Unless ``accept``: more than ``FAR_SHARE_LIMIT`` of the measured ranges lie beyond
        ``max_range_m``, or at least ``WHOLE_SHARE_LIMIT`` of them are whole numbers with a
        median over ``MILLIMETRE_MEDIAN_M`` metres. The message gives the evidence.
    """
    with np.errstate(over="ignore", invalid="ignore"):  # a max_range past float32: none far
        far = (range_m > max_range_m) & (range_m != np.inf)
    count = int(np.count_nonzero(far))
    if accept or (count == 0 and max_range_m <= MILLIMETRE_MEDIAN_M):
        return far, count  # below: the median can only pass 100 m if most ranges are far
    measured = int(np.count_nonzero(np.isfinite(range_m)))
    if measured == 0:
        return far, count
    sample = _measured_sample(range_m, measured)
    median = float(np.median(sample))
    share = count / measured
    if share > FAR_SHARE_LIMIT:
        largest = float(np.max(range_m[far]))
        millimetres = median > 10.0 * max_range_m and median / 1000.0 <= max_range_m
        hint = (
            "depth in millimetres? Convert it to metres (depth_scale 0.001 for a PNG), or give "
            "the sensor's real max_range"
            if millimetres
            else "give the sensor's real max_range, or check the units of the ranges"
        )
        raise FarRangesError(
            "range",
            f"{share:.0%} of the {measured:,} measured ranges lie beyond the sensor's "
            f"max_range of {max_range_m:g} m (median {_metres(median)}, "
            f"largest {_metres(largest)}): {hint}",
        )
    whole = float(np.mean(sample == np.round(sample)))
    if whole >= WHOLE_SHARE_LIMIT and median > MILLIMETRE_MEDIAN_M:
        raise FarRangesError(
            "range",
            f"the measured ranges look like millimetres, not metres: {whole:.0%} of them are "
            f"whole numbers and their median is {_metres(median)} "
            f"(max_range {max_range_m:g} m); "
            "convert them to metres (depth_scale 0.001 for a PNG)",
        )
    return far, count


@dataclass(frozen=True, eq=False)
class Scan:
    """One registered range map.

    Parameters
    ----------
    range_m : array (H, W)
        Ranges in metres in the sensor's range convention; ``+inf`` no return, NaN invalid.
        Any floating dtype; stored as read-only float32.
    T_W_S : array (4, 4)
        Sensor-to-world pose, ``x_W = R p_S + t``; must be rigid.
    sensor : Sensor
        The sensor model; ``range_m.shape`` must be ``(sensor.height, sensor.width)``.
    noise : NoiseModel or None
        Overrides the scene's noise model for this scan.
    accept_far_ranges : bool
        Keep a map whose measured ranges mostly lie beyond ``max_range`` or look like
        millimetres (:func:`check_far_ranges`); without it, :class:`FarRangesError`.

    Attributes
    ----------
    far_ranges : int
        Finite ranges beyond the sensor's ``max_range`` that were set to NaN (invalid).
    """

    range_m: np.ndarray
    T_W_S: np.ndarray
    sensor: Sensor
    noise: NoiseModel | None = field(default=None)
    accept_far_ranges: InitVar[bool] = False
    far_ranges: int = field(default=0, init=False)

    def __post_init__(self, accept_far_ranges: bool) -> None:
        if not isinstance(self.sensor, Sensor):
            raise InvalidScanError("sensor", f"must be a Sensor, got {type(self.sensor).__name__}")
        rng = self.range_m
        if not isinstance(rng, np.ndarray):
            raise InvalidScanError("range", f"must be a NumPy array, got {type(rng).__name__}")
        check_range_layout(rng.dtype, rng.shape, self.sensor.shape)
        with np.errstate(over="ignore", invalid="ignore"):
            rng32 = np.ascontiguousarray(rng, dtype=np.float32)
        if rng32 is not rng and rng.dtype.itemsize > 4 and np.isinf(rng32).any():
            # finite values past float32's range are far ranges, not "no return" (+inf)
            with np.errstate(invalid="ignore"):
                lost = np.isinf(rng32) & np.isfinite(rng)
            rng32[lost] = np.copysign(np.finfo(np.float32).max, rng32[lost])
        with np.errstate(invalid="ignore"):
            bad = int(np.count_nonzero(rng32 <= 0.0))
        if bad:
            raise InvalidScanError(
                "range",
                f"{bad} pixels are <= 0 or -inf; ranges are positive metres, "
                "invalid pixels must be NaN",
            )
        far, count = check_far_ranges(rng32, self.sensor.max_range, bool(accept_far_ranges))
        if rng32 is rng:
            rng32 = rng32.copy()
        if count:
            rng32[far] = np.nan
        del far
        rng32.setflags(write=False)
        object.__setattr__(self, "far_ranges", count)
        object.__setattr__(self, "range_m", rng32)
        T = check_pose(self.T_W_S)
        T.setflags(write=False)
        object.__setattr__(self, "T_W_S", T)
        if self.noise is not None and not isinstance(self.noise, NoiseModel):
            raise InvalidScanError(
                "noise", f"must be a NoiseModel, got {type(self.noise).__name__}"
            )

    @property
    def shape(self) -> tuple[int, int]:
        return self.sensor.shape

    def points_W(self) -> np.ndarray:
        """World points (n, 3) of the finite measurements (no-return and invalid pixels out)."""
        v, u = np.nonzero(np.isfinite(self.range_m))
        p_S = self.sensor.unproject(u, v, self.range_m[v, u])
        R = self.T_W_S[:3, :3]
        t = self.T_W_S[:3, 3]
        return p_S @ R.T + t


@dataclass(frozen=True)
class FusionParams:
    """How a scene turns scans into certainty (METHOD §1, §4 step 2).

    Parameters
    ----------
    noise : NoiseModel
        Default noise model; a scan's own ``noise`` overrides it.
    filter : {"none", "mean5", "median3"}
        Range-map filter applied before fusion.
    max_discontinuity : float or None
        Depth-discontinuity test: a point whose four neighbouring ranges spread by more gets
        no information. ``None`` disables it.
    no_return : {"free", "invalid"}
        ``"free"``: a no-return pixel (``+inf``) is a measurement at the sensor's ``max_range``
        and carves free space; ``"invalid"``: it is ignored.
    """

    noise: NoiseModel
    filter: str = PARAMS["filter"].default
    max_discontinuity: float | None = None
    no_return: str = PARAMS["no_return"].default

    def __post_init__(self) -> None:
        if not isinstance(self.noise, NoiseModel):
            raise InvalidInputError(
                "noise", f"must be a NoiseModel, got {type(self.noise).__name__}"
            )
        # each field as declared in engine/params.py
        for param in params_of("fusion"):
            object.__setattr__(self, param.name, param.validate(getattr(self, param.name)))

    def to_dict(self) -> dict[str, Any]:
        return {
            "noise": self.noise.to_dict(),
            "filter": self.filter,
            "max_discontinuity": self.max_discontinuity,
            "no_return": self.no_return,
        }

    @staticmethod
    def from_dict(data: dict[str, Any]) -> FusionParams:
        data = current_names(data)
        return FusionParams(
            noise=NoiseModel.from_dict(data["noise"]),
            filter=data.get("filter", PARAMS["filter"].default),
            max_discontinuity=data.get("max_discontinuity"),
            no_return=data.get("no_return", PARAMS["no_return"].default),
        )


@dataclass(frozen=True, eq=False)
class PreparedScan:
    """A scan as the kernels take it (see :func:`prepare_scan`)."""

    range_m: np.ndarray  # float32 (H, W): finite or NaN
    surface_m: np.ndarray  # float32 (H, W): measured surface only (no-return pixels NaN)
    kind: int
    params: np.ndarray
    table: np.ndarray
    M: np.ndarray  # (3, 3) R^T: p_S = M @ x_W + c
    c: np.ndarray  # (3,)
    T_W_S: np.ndarray
    eps: float  # eps0 of METHOD §1: eps(r) = eps + eps_per_m * r
    eps_per_m: float
    rho: float
    falloff: float  # < 0: eps at that range
    shape: int
    q_rho: int
    max_discontinuity: float  # < 0: no discontinuity test
    # the tile tests' statistics, computed on first use (see pyramid)
    _pyramid: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(
        default_factory=list, repr=False
    )

    @property
    def origin_W(self) -> np.ndarray:
        return self.T_W_S[:3, 3]

    def quad_bounds(self, scratch: Scratch | None = None) -> np.ndarray:
        """Per-quad bounds of the range map (:func:`engine._sampling.quad_bounds`), in
        ``scratch``'s array when given. The first call also builds the tile tests'
        :meth:`pyramid` from them, in the same pass: mapping-mode allocation needs no
        pyramid, and the fusion pass computes the bounds anyway, so a batch computes them
        once per scan instead of twice."""
        args = (
            self.kind, self.params, self.range_m, self.eps, self.eps_per_m, self.falloff,
            self.max_discontinuity, scratch,
        )  # fmt: skip
        if self._pyramid:
            return _sampling.quad_bounds_array(*args)
        bounds, pyramid = _sampling.bounds_and_pyramid(*args)
        self._pyramid.append(pyramid)
        return bounds

    def pyramid(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The per-quad bounds reduced over blocks of quads, in a pyramid of levels
        (:func:`engine._sampling.bounds_and_pyramid`): ``free`` (float64: nearer than it, a
        point is in free space), ``reach`` (float64: farther than it, nothing is informed)
        and ``levels`` (int64 (L, 3)). Computed on first use (see :meth:`quad_bounds`)."""
        if not self._pyramid:
            self.quad_bounds()
        return self._pyramid[0]

    @property
    def has_pyramid(self) -> bool:
        return bool(self._pyramid)

    @property
    def reach_max(self) -> float:
        """The largest reach of any quad; -inf when the scan informs nothing."""
        _, reach, levels = self.pyramid()
        return float(reach[levels[-1, 0]])

    def noise_args(self) -> tuple[float, float, float, float, int, int]:
        return self.eps, self.eps_per_m, self.rho, self.falloff, self.shape, self.q_rho

    def band_lo_hi(self, r: float, margin_m: float) -> tuple[float, float]:
        """Distances ``[r - eps - margin, r + eps + falloff]`` of the surface band at range r."""
        eps = self.eps + self.eps_per_m * r
        f = self.falloff if self.falloff > 0.0 else eps
        return r - eps - margin_m, r + eps + f


def prepare_scan(scan: Scan, params: FusionParams) -> PreparedScan:
    """Apply the filter and the no-return policy, and precompute what kernels need (the
    tile tests' pyramid waits for its first use: :meth:`PreparedScan.pyramid`)."""
    # the scan's own read-only array when neither the filter nor no-return pixels change
    # it (a prepared scan stays cached while its volume lives: copies would double it)
    rng = np.asarray(filter_range(scan.range_m, params.filter), dtype=np.float32)
    rng.setflags(write=False)
    surface = rng
    no_return = rng == np.inf  # np.isposinf is about 3x slower on float32
    if no_return.any():
        surface = rng.copy()
        surface[no_return] = np.nan
        surface.setflags(write=False)
        if params.no_return == "free":
            rng = rng.copy()
            rng[no_return] = scan.sensor.max_range
            rng.setflags(write=False)
        else:
            rng = surface
    noise = scan.noise if scan.noise is not None else params.noise
    eps0, eps1, rho, falloff, shape, q_rho = noise.kernel_args()
    max_disc = -1.0 if params.max_discontinuity is None else params.max_discontinuity
    kind, sensor_params, table = scan.sensor.kernel_args()
    R = scan.T_W_S[:3, :3]
    M = np.ascontiguousarray(R.T)
    c = np.ascontiguousarray(-M @ scan.T_W_S[:3, 3])
    return PreparedScan(
        range_m=rng,
        surface_m=surface,
        kind=kind,
        params=sensor_params,
        table=table,
        M=M,
        c=c,
        T_W_S=scan.T_W_S,
        eps=eps0,
        eps_per_m=eps1,
        rho=rho,
        falloff=falloff,
        shape=shape,
        q_rho=q_rho,
        max_discontinuity=max_disc,
    )
