"""Surface extraction speed on the fused synthetic room (issue: meshing).

For each voxel size, fuses the room's frames (mapping mode) and times, in the same process
on the same data: rangefuse's tiled extraction without and with edge refinement,
scikit-image's marching cubes on the same field made dense (unknown voxels masked), and
Open3D's ``extract_triangle_mesh`` on its own TSDF of the same frames (the ``bench`` extra).
Each extraction runs once to warm up (compile) and is then timed as the best of three.

    python benchmarks/meshing.py            # 100 frames at 2 cm and 1 cm
    python benchmarks/meshing.py --quick    # 10 frames at 4 cm (a smoke run)
"""

from __future__ import annotations

import argparse
import resource
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _peers import Open3DTSDF, depth_images, open3d_available
from rangefuse.engine import FusionParams, GridSpec, NoiseModel, Volume
from rangefuse.engine.synth import make_dataset


def _best(fn: Callable[[], int], repeat: int = 3) -> tuple[int, float]:
    fn()  # warm-up: compile or load the kernels
    best = np.inf
    tris = 0
    for _ in range(repeat):
        t0 = time.perf_counter()
        tris = fn()
        best = min(best, time.perf_counter() - t0)
    return tris, float(best)


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def run(frames: int, h: float, tile: int, skimage_limit: int) -> list[tuple[str, int, float]]:
    data = make_dataset("room", views=frames)
    volume = Volume(GridSpec(h, tile, "mapping"), FusionParams(NoiseModel(eps=2 * h, rho=0.05)))
    volume.add_many(data.scans)
    rows = []
    rows.append(("rangefuse", *_best(lambda: volume.extract_mesh(refine=False).n_faces)))
    rows.append(("rangefuse refined", *_best(lambda: volume.extract_mesh(refine=True).n_faces)))
    dense = volume.to_dense()
    if dense.logodds.size <= skimage_limit:
        from skimage.measure import marching_cubes

        field = dense.logodds
        known = np.isfinite(field)
        filled = np.where(known, field, 0.0).astype(np.float32)
        # a cube is meshed when its 8 corners are known (as rangefuse's mapping mode does);
        # skimage tests its mask at a cube's upper corner
        cube = known.copy()
        cube[:-1] &= known[1:]
        cube[:, :-1] &= cube[:, 1:]
        cube[:, :, :-1] &= cube[:, :, 1:]
        mask = np.zeros_like(cube)
        mask[1:, 1:, 1:] = cube[:-1, :-1, :-1]

        def skimage_mc() -> int:
            _, faces, _, _ = marching_cubes(filled, 0.0, mask=mask, method="lorensen")
            return len(faces)

        rows.append(("skimage (dense)", *_best(skimage_mc)))
    else:
        rows.append(("skimage (dense)", -1, float("nan")))
    del dense
    if open3d_available():
        tsdf = Open3DTSDF(h, data.sensor)  # type: ignore[arg-type]
        poses = [scan.T_W_S for _, scan in data.scans]
        tsdf.integrate_all(depth_images(data.scans), tsdf.extrinsics(poses))
        rows.append(("open3d", *_best(lambda: tsdf.extract_triangle_mesh()[0])))
    else:
        rows.append(("open3d (not installed)", -1, float("nan")))
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="10 frames at 4 cm")
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--voxel", type=float, action="append", help="metres (repeatable)")
    parser.add_argument("--tile-size", type=int, default=16)
    parser.add_argument(
        "--skimage-limit", type=int, default=400_000_000, help="largest dense grid for skimage"
    )
    args = parser.parse_args()
    frames = 10 if args.quick else args.frames
    voxels = [0.04] if args.quick else (args.voxel or [0.02, 0.01])
    header = (
        f"{'voxel':>6} {'frames':>6} {'extractor':18} {'triangles':>10} {'time s':>8} "
        f"{'Mtri/s':>7} {'vs open3d':>9} {'peak RSS MB':>11}"
    )
    print(header)
    print("-" * len(header))
    if not open3d_available():
        print("(open3d is not installed: `make bench` installs the bench extra)")
    for h in voxels:
        rows = run(frames, h, args.tile_size, args.skimage_limit)
        o3d_time = rows[-1][2]
        for name, tris, seconds in rows:
            speed = tris / seconds / 1e6 if tris >= 0 else float("nan")
            tris = max(tris, 0)
            print(
                f"{h:6.3f} {frames:6d} {name:18} {tris:10d} {seconds:8.3f} {speed:7.2f} "
                f"{o3d_time / seconds:9.2f} {_rss_mb():11.0f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
