"""A slow, dense, obviously correct NumPy reference of METHOD.md §1-2.

Written independently of the engine's kernels (it reads sensors through their
FORMAT.md dictionaries, not their kernel parameter vectors) and in float64
throughout, without quantisation. Tests compare the engine to it voxel by voxel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from rangefuse.engine import FusionParams, NoiseModel, Scan
from scipy.special import erfc


def project(sensor: dict, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(u, v, d) of sensor-frame points p (n, 3); u = NaN where the point has no pixel."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    model = sensor["model"]
    W, H = sensor["width"], sensor["height"]
    with np.errstate(divide="ignore", invalid="ignore"):
        if model == "pinhole":
            u = sensor["fx"] * x / z + sensor["cx"]
            v = sensor["fy"] * y / z + sensor["cy"]
            d = z if sensor["range_convention"] == "z" else np.sqrt(x * x + y * y + z * z)
            u = np.where(z > 0, u, np.nan)
        elif model in ("spherical", "cylindrical"):
            span = sensor["az_max"] - sensor["az_min"]
            daz = span / W if sensor.get("wrap", False) else span / (W - 1)
            u = np.mod(np.arctan2(y, x) - sensor["az_min"], 2 * math.pi) / daz
            rho = np.hypot(x, y)
            if model == "spherical":
                el = np.arctan2(z, rho)
                d = np.sqrt(x * x + y * y + z * z)
                table = sensor.get("elevations")
                if table is not None:
                    table = np.asarray(table)
                    v = np.interp(-el, -table, np.arange(H, dtype=np.float64))
                    v = np.where(el > table[0], -1.0, np.where(el < table[-1], H, v))
                else:
                    v = (sensor["el_max"] - el) / ((sensor["el_max"] - sensor["el_min"]) / (H - 1))
                u = np.where(d > 0, u, np.nan)
            else:
                if sensor.get("axial", "perspective") == "linear":
                    v = sensor["cy"] - sensor["fy"] * z
                else:
                    v = sensor["cy"] - sensor["fy"] * z / rho
                d = (
                    rho
                    if sensor["range_convention"] == "radial"
                    else np.sqrt(x * x + y * y + z * z)
                )
                u = np.where(rho > 0, u, np.nan)
        elif model == "orthographic":
            u = x / sensor["sx"] + sensor.get("cx", 0.0)
            v = y / sensor["sy"] + sensor.get("cy", 0.0)
            d = z
            u = np.where(z >= 0, u, np.nan)
        else:
            raise ValueError(model)
    return u, v, d


def wraps(sensor: dict) -> bool:
    return sensor["model"] in ("spherical", "cylindrical") and bool(sensor.get("wrap", False))


def bilinear(sensor: dict, img: np.ndarray, u: np.ndarray, v: np.ndarray, max_disc):
    """Interpolated range and validity at (u, v) under METHOD's exact conventions."""
    H, W = img.shape
    ok = np.isfinite(u) & (v >= 0) & (v <= H - 1)
    if wraps(sensor):
        ok &= (u >= 0) & (u < W)
    else:
        ok &= (u >= 0) & (u <= W - 1)
    uu = np.where(ok, u, 0.0)
    vv = np.where(ok, v, 0.0)
    u0 = np.floor(uu).astype(np.int64)
    v0 = np.minimum(np.floor(vv).astype(np.int64), H - 2)
    if wraps(sensor):
        u1 = (u0 + 1) % W
    else:
        u0 = np.minimum(u0, W - 2)
        u1 = u0 + 1
    fu = uu - u0
    fv = vv - v0
    r00, r01 = img[v0, u0], img[v0, u1]
    r10, r11 = img[v0 + 1, u0], img[v0 + 1, u1]
    corners = np.stack([r00, r01, r10, r11])
    ok &= np.all(np.isfinite(corners), axis=0)
    if max_disc is not None:
        spread = np.max(corners, axis=0) - np.min(corners, axis=0)  # NaN where invalid
        with np.errstate(invalid="ignore"):
            ok &= spread <= max_disc
    r = (1 - fv) * ((1 - fu) * r00 + fu * r01) + fv * ((1 - fu) * r10 + fu * r11)
    return np.where(ok, r, np.nan), ok


def filter_ref(img: np.ndarray, name: str) -> np.ndarray:
    """5x5 mean of finite neighbours / 3x3 median of non-NaN neighbours (inf sorts last)."""
    if name == "none":
        return img.astype(np.float64)
    H, W = img.shape
    out = np.empty((H, W))
    k = 2 if name == "mean5" else 1
    for v in range(H):
        for u in range(W):
            c = img[v, u]
            win = (
                img[max(0, v - k) : v + k + 1, max(0, u - k) : u + k + 1].astype(np.float64).ravel()
            )
            if name == "mean5":
                out[v, u] = c if not np.isfinite(c) else win[np.isfinite(win)].mean()
            else:
                out[v, u] = c if np.isnan(c) else np.median(win[~np.isnan(win)])
    return out


def certainty(alpha: np.ndarray, eps: np.ndarray, f: np.ndarray, noise: NoiseModel):
    rho = noise.rho
    if noise.shape == "linear":
        front = np.where(alpha < -eps, rho, rho + (0.5 - rho) * (alpha + eps) / eps)
        c_eps = 1.0 - rho
    else:
        sigma = eps * math.sqrt(2.0 / math.pi)
        front = rho + (1 - 2 * rho) * 0.5 * erfc(-alpha / (sigma * math.sqrt(2.0)))
        c_eps = rho + (1 - 2 * rho) * 0.5 * erfc(-eps / (sigma * math.sqrt(2.0)))
    back = c_eps - (c_eps - 0.5) * (alpha - eps) / f
    return np.where(alpha <= eps, front, back)


@dataclass
class ReferenceVolume:
    logodds: np.ndarray  # float64, NaN unknown
    count: np.ndarray  # informing scans per voxel
    band: np.ndarray  # bool: |alpha| <= eps for some scan with a measured surface there


def fuse(
    scans: list[Scan], params: FusionParams, first_voxel, shape, voxel_size
) -> ReferenceVolume:
    """Dense fusion over voxels ``first_voxel + [0, shape)`` of the global lattice."""
    idx = np.stack(np.meshgrid(*[np.arange(n) for n in shape], indexing="ij"), -1).reshape(-1, 3)
    x_W = (np.asarray(first_voxel) + idx + 0.5) * voxel_size
    total = np.zeros(len(x_W))
    count = np.zeros(len(x_W), np.int64)
    band = np.zeros(len(x_W), bool)
    for scan in scans:
        sensor = scan.sensor.to_dict()
        noise = scan.noise or params.noise
        # the engine keeps range maps in float32, filtered ones too
        raw = filter_ref(scan.range_m, params.filter).astype(np.float32).astype(np.float64)
        img = raw.copy()
        no_return = np.isposinf(img)
        img[no_return] = sensor["max_range"] if params.no_return == "free" else np.nan
        surface = raw.copy()
        surface[no_return] = np.nan
        T = scan.T_W_S
        p_S = (x_W - T[:3, 3]) @ T[:3, :3]
        u, v, d = project(sensor, p_S)
        r, ok = bilinear(sensor, img, u, v, params.max_discontinuity)
        alpha = d - r
        eps = noise.eps + noise.eps_per_m * r
        f = eps if noise.falloff is None else np.full_like(eps, noise.falloff)
        with np.errstate(invalid="ignore"):
            informed = ok & (alpha <= eps + f)
            c = certainty(alpha, eps, f, noise)
        total[informed] += np.log(c[informed] / (1 - c[informed]))
        count[informed] += 1
        _, on_surface = bilinear(sensor, surface, u, v, params.max_discontinuity)
        with np.errstate(invalid="ignore"):
            band |= on_surface & ok & (np.abs(alpha) <= eps)
    logodds = np.where(count > 0, total, np.nan)
    return ReferenceVolume(logodds.reshape(shape), count.reshape(shape), band.reshape(shape))
