"""Hashes of what `rangefuse fuse` writes, to show that a change keeps the same bits.

Fuses the synthetic room, street and object in mapping and closed mode, in memory and with
``--store`` (then ``remove`` of one scan and ``add`` of it again), through the installed
``rangefuse`` command, and prints the SHA-256 of the ``--grid-out`` log-odds and of the PLY
of each run. ``--save FILE`` records the hashes, ``--check FILE`` compares with a record
(exit status 1 on any difference)::

    python benchmarks/same_bits.py --save before.json     # before the change
    python benchmarks/same_bits.py --check before.json    # after it

Not a timed benchmark: it prints hashes, and the wall time of each run for orientation.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

#: (scene, synth options, voxel size, fuse options) per case; closed mode takes the region
#: of interest that ``synth`` writes into ``scene.json``.
CASES = {
    "room": (["--views", "8", "--noise", "gaussian:0.005"], 0.04, ["--filter", "median3"]),
    "street": (["--length", "16"], 0.1, []),
    "object": (["--views", "12"], 0.012, ["--max-discontinuity", "0.05"]),
}


def _rangefuse() -> str:
    return str(Path(sys.executable).with_name("rangefuse"))


def _run(*args: str) -> None:
    subprocess.run([_rangefuse(), *args], check=True, capture_output=True, text=True)


def _hash_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()[:16]


def _hash_grid(path: Path) -> str:
    with np.load(path) as z:
        digest = hashlib.sha256(np.ascontiguousarray(z["logodds"]).tobytes())
        digest.update(np.asarray(z["origin"], np.float64).tobytes())
    return digest.hexdigest()[:16]


def run_cases(work: Path) -> dict[str, dict[str, str]]:
    results: dict[str, dict[str, str]] = {}
    for scene, (synth_opts, voxel, fuse_opts) in CASES.items():
        data = work / scene
        _run("synth", scene, str(data), *synth_opts)
        bounds = json.loads((data / "scene.json").read_text())["bounds"]
        first_scan = sorted((data / "scans").glob("*.npz"))[0]
        for mode in ("mapping", "closed"):
            h = voxel if mode == "mapping" else 2 * voxel
            opts = ["--voxel-size", str(h), "--mode", mode, "--quiet", *fuse_opts]
            if mode == "closed":
                opts += ["--bounds", *(str(b) for b in bounds)]
            for where in ("memory", "store"):
                name = f"{scene}-{mode}-{where}"
                out = work / name
                t0 = time.perf_counter()
                extra = ["--store", str(work / f"{name}.store")] if where == "store" else []
                _run(
                    "fuse", str(data), *opts, *extra,
                    "--grid-out", f"{out}.npz", "-o", f"{out}.ply",
                )  # fmt: skip
                results[name] = {
                    "grid": _hash_grid(Path(f"{out}.npz")),
                    "ply": _hash_file(Path(f"{out}.ply")),
                    "seconds": f"{time.perf_counter() - t0:.1f}",
                }
                if where == "store":
                    store = str(work / f"{name}.store")
                    again = work / f"{scene}-{mode}-store-remove-add"
                    t0 = time.perf_counter()
                    _run("remove", store, first_scan.stem)
                    _run("add", store, str(first_scan), "--quiet")
                    _run("extract", store, "--grid-out", f"{again}.npz", "-o", f"{again}.ply")
                    results[again.name] = {
                        "grid": _hash_grid(Path(f"{again}.npz")),
                        "ply": _hash_file(Path(f"{again}.ply")),
                        "seconds": f"{time.perf_counter() - t0:.1f}",
                    }
    return results


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--save", type=Path, help="write the hashes to this JSON file")
    parser.add_argument("--check", type=Path, help="compare with hashes saved earlier")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="rangefuse-bits-") as tmp:
        results = run_cases(Path(tmp))
    expected = json.loads(args.check.read_text()) if args.check else {}
    bad = 0
    print(f"{'run':34} {'grid':16} {'ply':16} {'s':>6}  same")
    for name, r in results.items():
        same = ""
        if expected:
            ok = expected.get(name, {}).get("grid") == r["grid"] and (
                expected.get(name, {}).get("ply") == r["ply"]
            )
            same = "yes" if ok else "NO"
            bad += not ok
        print(f"{name:34} {r['grid']:16} {r['ply']:16} {r['seconds']:>6}  {same}")
    if args.save:
        args.save.write_text(json.dumps(results, indent=1) + "\n")
    if expected:
        print("all the same" if not bad else f"{bad} runs differ")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
