"""The ``rangefuse`` command line (service/cli.py): synth, fuse, options and error exits.

A few cases run the installed console script (or ``python -m rangefuse.service.cli``) as a real
subprocess; the rest call :func:`service.cli.main` in-process, which is faster. Every
fused grid is compared bit for bit (NaN positions included) with the same scans fused
in-process through :class:`engine.Volume` with the parameters the CLI documents.
"""

from __future__ import annotations

import io
import json
import os
import subprocess
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
from rangefuse.engine import DenseGrid, FusionParams, GridSpec, NoiseModel, Scan, Volume
from rangefuse.engine.grid import Bounds
from rangefuse.engine.synth import SyntheticDataset, make_dataset, parse_noise
from rangefuse.service._progress import ProgressBar
from rangefuse.service.cli import main
from rangefuse.storage import open_dataset, read_grid, write_dataset

ROOT = Path(__file__).resolve().parents[1]
RANGEFUSE = Path(sys.executable).parent / "rangefuse"
H = 0.04
VIEWS = 3


def run_main(argv: Sequence[Any], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str]:
    """``main(argv)`` in-process: exit status (argparse errors included), stdout, stderr."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:
        code = int(exc.code or 0)
    out, err = capsys.readouterr()
    return code, out, err


def run_subprocess(*argv: Any, module: bool = False) -> subprocess.CompletedProcess[str]:
    """The installed ``rangefuse`` script, or ``python -m rangefuse.service.cli`` with
    ``module``."""
    env = dict(os.environ)
    head = [sys.executable, "-m", "rangefuse.service.cli"] if module else [str(RANGEFUSE)]
    return subprocess.run(
        [*head, *map(str, argv)],
        capture_output=True,
        text=True,
        cwd=ROOT,
        env=env,
        timeout=300,
        check=False,
    )


def fuse_in_process(
    scans: Sequence[tuple[str, Scan]],
    voxel_size: float = H,
    *,
    mode: str = "mapping",
    bounds: Sequence[float] | None = None,
    tile_size: int = 16,
    eps: float | None = None,
    eps_per_m: float = 0.0,
    rho: float = 0.05,
    falloff: float | None = None,
    shape: str = "linear",
    filter: str = "none",
    max_discontinuity: float | None = None,
    no_return: str = "free",
) -> DenseGrid:
    """What ``rangefuse fuse`` documents: eps defaults to 2 voxels, rho to 0.05."""
    noise = NoiseModel(
        eps=2.0 * voxel_size if eps is None else eps,
        eps_per_m=eps_per_m,
        rho=rho,
        falloff=falloff,
        shape=shape,
    )
    params = FusionParams(
        noise, filter=filter, max_discontinuity=max_discontinuity, no_return=no_return
    )
    box = None if bounds is None else cast("Bounds", tuple(bounds))
    volume = Volume(GridSpec(voxel_size, tile_size, mode, box), params)
    volume.add_many(list(scans))
    return volume.to_dense(bounds)


def assert_same_grid(a: DenseGrid, b: DenseGrid) -> None:
    """Bit for bit: shape, origin, voxel size, NaN positions and every known value."""
    assert a.logodds.shape == b.logodds.shape
    assert a.logodds.dtype == b.logodds.dtype == np.float32
    assert np.array_equal(a.origin, b.origin)
    assert a.voxel_size == b.voxel_size
    assert np.array_equal(a.first_voxel, b.first_voxel)
    nan_a, nan_b = np.isnan(a.logodds), np.isnan(b.logodds)
    assert np.array_equal(nan_a, nan_b)
    assert np.array_equal(a.logodds[~nan_a].view(np.uint32), b.logodds[~nan_b].view(np.uint32))


def same_grid(a: DenseGrid, b: DenseGrid) -> bool:
    try:
        assert_same_grid(a, b)
    except AssertionError:
        return False
    return True


def no_leftovers(folder: Path) -> list[str]:
    """Temporary files that an interrupted atomic write would leave."""
    return [p.name for p in folder.iterdir() if p.name.endswith(".tmp")]


# --- fixtures ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def object_data() -> SyntheticDataset:
    return make_dataset("object", views=VIEWS)


@pytest.fixture(scope="module")
def object_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The object scene written by ``rangefuse synth`` (in-process)."""
    out = tmp_path_factory.mktemp("cli") / "object"
    assert main(["synth", "object", str(out), "--views", str(VIEWS)]) == 0
    return out


@pytest.fixture(scope="module")
def object_scans(object_dir: Path) -> list[tuple[str, Scan]]:
    return list(open_dataset(object_dir).scans())


@pytest.fixture(scope="module")
def bounds(object_data: SyntheticDataset) -> list[float]:
    return [round(b, 3) for b in object_data.bounds]


@pytest.fixture(scope="module")
def default_grid(object_scans: list[tuple[str, Scan]], bounds: list[float]) -> DenseGrid:
    return fuse_in_process(object_scans, bounds=bounds)


# --- end to end, real subprocesses ------------------------------------------------------------


def test_console_script_synth_then_fuse(tmp_path: Path, object_data: SyntheticDataset) -> None:
    data_dir = tmp_path / "object"
    synth = run_subprocess("synth", "object", data_dir, "--views", VIEWS)
    assert synth.returncode == 0, synth.stderr
    assert f"wrote {VIEWS} pinhole scans of the object scene" in synth.stdout
    grid_out = tmp_path / "out" / "grid.npz"
    grid_out.parent.mkdir()  # a missing one is refused (tests/test_first_hour.py)
    fuse = run_subprocess("fuse", data_dir, "--voxel-size", H, "--grid-out", grid_out, module=True)
    assert fuse.returncode == 0, fuse.stderr
    assert f"fused {VIEWS} scans into" in fuse.stdout
    assert f"grid to {grid_out}" in fuse.stdout
    assert f"{VIEWS}/{VIEWS} scans" in fuse.stderr  # the progress bar
    assert "Traceback" not in fuse.stderr
    assert [p.name for p in grid_out.parent.iterdir()] == ["grid.npz"]
    grid = read_grid(grid_out)
    # Mapping mode without bounds: the bounding box of the tiles, whole tiles of 16 voxels.
    assert all(n % 16 == 0 for n in grid.logodds.shape)
    assert np.isfinite(grid.logodds).any() and np.isnan(grid.logodds).any()
    assert_same_grid(grid, fuse_in_process(list(open_dataset(data_dir).scans())))
    # The files hold exactly the rendered scans: fusing them from memory is the same.
    assert_same_grid(grid, fuse_in_process(object_data.scans))


def test_console_script_error_exit(tmp_path: Path, object_dir: Path) -> None:
    broken = tmp_path / "broken"
    write_dataset(broken, *_dataset_parts(object_dir))
    (broken / "scans" / "scan_0001.npz").write_bytes(b"PK\x03\x04 not really a zip")
    grid_out = tmp_path / "grid.npz"
    proc = run_subprocess("fuse", broken, "--voxel-size", H, "--grid-out", grid_out)
    assert proc.returncode == 2
    assert "rangefuse fuse: error:" in proc.stderr
    assert "scan_0001.npz" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not grid_out.exists()
    usage = run_subprocess("fuse", broken, "--voxel-size", "abc")
    assert usage.returncode == 2
    assert "--voxel-size: not a number: 'abc'" in usage.stderr
    assert "Traceback" not in usage.stderr


def _dataset_parts(root: Path) -> tuple[Any, list[tuple[str, Scan]]]:
    dataset = open_dataset(root)
    return dataset.sensor, list(dataset.scans())


# --- synth ------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("scene", "views", "noise", "model", "convention"),
    [
        ("object", 2, "gaussian:0.002,dropouts:0.01", "pinhole", "ray"),
        ("room", 2, "uniform:0.01,spikes:0.001,background:nan", "pinhole", "z"),
        ("street", 2, "gaussian:0.01", "spherical", "ray"),
    ],
)
def test_synth_writes_a_dataset(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    scene: str,
    views: int,
    noise: str,
    model: str,
    convention: str,
) -> None:
    out = tmp_path / scene
    argv = ["synth", scene, out, "--views", views, "--noise", noise, "--seed", 7]
    code, stdout, err = run_main(argv, capsys)
    assert code == 0, err
    assert f"wrote {views} {model} scans of the {scene} scene to {out}" in stdout
    dataset = open_dataset(out)
    assert len(dataset) == views
    assert dataset.names == [f"scan_{k:04d}" for k in range(views)]
    assert dataset.sensor is not None
    assert dataset.sensor.model == model
    assert dataset.sensor.range_convention == convention
    expected = make_dataset(scene, views=views, noise=parse_noise(noise), seed=7)
    assert dataset.sensor == expected.sensor
    for (name, got), (want_name, want) in zip(dataset.scans(), expected.scans, strict=True):
        assert name == want_name
        assert np.array_equal(got.range_m.view(np.uint32), want.range_m.view(np.uint32))
        assert np.array_equal(got.T_W_S, want.T_W_S)
    meta = json.loads((out / "scene.json").read_text())
    assert meta["scene"] == scene
    assert meta["noise"] == noise
    assert meta["seed"] == 7
    assert meta["bounds"] == list(expected.bounds)


def test_synth_seed_and_rerun(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def ranges(out: Path) -> list[np.ndarray]:
        return [s.range_m for _, s in open_dataset(out).scans()]

    base = ["object", "--views", 2, "--noise", "gaussian:0.01"]
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        assert (
            run_main(["synth", base[0], tmp_path / name, *base[1:], "--seed", seed], capsys)[0] == 0
        )
    a, b, c = ranges(tmp_path / "a"), ranges(tmp_path / "b"), ranges(tmp_path / "c")
    assert all(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, b, strict=True))
    assert not any(np.array_equal(x, y, equal_nan=True) for x, y in zip(a, c, strict=True))
    # Writing the same dataset again over itself is fine (make run does it every time).
    code, _, err = run_main(["synth", "object", tmp_path / "a", *base[1:], "--seed", 1], capsys)
    assert code == 0, err
    assert all(
        np.array_equal(x, y, equal_nan=True) for x, y in zip(ranges(tmp_path / "a"), a, strict=True)
    )


def test_synth_street_length(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(["synth", "street", tmp_path / "s", "--length", 4], capsys)
    assert code == 0, err
    assert len(open_dataset(tmp_path / "s")) == 2  # one scan per 2 m


SYNTH_ERRORS: dict[str, tuple[list[str], str]] = {
    "views 0": (["object", "{out}", "--views", "0"], "--views: must be at least 1"),
    "views two": (["object", "{out}", "--views", "two"], "--views: not an integer"),
    "unknown scene": (["cave", "{out}"], "invalid choice: 'cave'"),
    "unknown noise": (["object", "{out}", "--noise", "pink:0.1"], "unknown kind 'pink'"),
    "negative noise": (["object", "{out}", "--noise", "gaussian:-1"], "gaussian must be >= 0"),
    "spikes 2": (["object", "{out}", "--noise", "spikes:2"], "spikes is a fraction"),
    "length for object": (["object", "{out}", "--length", "10"], "length_m: applies to the street"),
    "negative length": (["street", "{out}", "--length=-3"], "--length: must be a positive number"),
    "OUT is a file": (["object", "{file}"], "exists and is not a directory"),
    "OUT under a file": (["object", "{file}/sub"], "is not a directory"),
}


@pytest.mark.parametrize("case", list(SYNTH_ERRORS))
def test_synth_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    args, message = SYNTH_ERRORS[case]
    (tmp_path / "file").write_text("not a folder")
    argv = ["synth", *(a.format(out=tmp_path / "out", file=tmp_path / "file") for a in args)]
    code, _, err = run_main(argv, capsys)
    assert code == 2
    assert message in err, err
    assert "Traceback" not in err
    assert not (tmp_path / "out").exists()
    assert (tmp_path / "file").read_text() == "not a folder"


def test_synth_refuses_to_mix_datasets(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "obj"
    assert run_main(["synth", "object", out, "--views", 3], capsys)[0] == 0
    before = {p.name: p.read_bytes() for p in (out / "scans").iterdir()}
    code, _, err = run_main(["synth", "object", out, "--views", 2], capsys)
    assert code == 2
    assert "already holds 1 scans that this run would not replace (scan_0002.npz" in err
    assert {p.name: p.read_bytes() for p in (out / "scans").iterdir()} == before


# --- fuse: parameters are the documented ones --------------------------------------------------


def test_fuse_defaults_are_two_voxels_and_rho_005(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    object_dir: Path,
    default_grid: DenseGrid,
    bounds: list[float],
    object_scans: list[tuple[str, Scan]],
) -> None:
    grid_out = tmp_path / "g.npz"
    code, out, err = run_main(
        ["fuse", object_dir, "--voxel-size", H, "--bounds", *bounds, "--grid-out", grid_out],
        capsys,
    )
    assert code == 0, err
    assert "x".join(map(str, default_grid.logodds.shape)) + " grid" in out
    grid = read_grid(grid_out)
    assert_same_grid(grid, default_grid)
    explicit = fuse_in_process(object_scans, bounds=bounds, eps=2 * H, rho=0.05, tile_size=16)
    assert_same_grid(grid, explicit)
    # The region of interest: voxels whose centres lie in the bounds.
    lo = np.asarray(bounds[:3])
    hi = np.asarray(bounds[3:])
    assert np.all(grid.origin >= lo) and np.all(grid.origin - H < lo)
    far = grid.origin + (np.array(grid.logodds.shape) - 1) * H
    assert np.all(far <= hi) and np.all(far + H > hi)


OPTION_CASES: dict[str, tuple[list[Any], dict[str, Any]]] = {
    "eps": (["--eps", 0.1], {"eps": 0.1}),
    "eps-per-m": (["--eps-per-m", 0.05], {"eps_per_m": 0.05}),
    "rho": (["--rho", 0.2], {"rho": 0.2}),
    "falloff": (["--falloff", 0.2], {"falloff": 0.2}),
    "shape erf": (["--shape", "erf"], {"shape": "erf"}),
    "filter median3": (["--filter", "median3"], {"filter": "median3"}),
    "filter mean5": (["--filter", "mean5"], {"filter": "mean5"}),
    "max-discontinuity": (["--max-discontinuity", 0.05], {"max_discontinuity": 0.05}),
    "no-return invalid": (["--no-return", "invalid"], {"no_return": "invalid"}),
    "tile-size 8": (["--tile-size", 8], {"tile_size": 8}),
    "several": (
        ["--eps", 0.06, "--rho", 0.1, "--shape", "erf", "--filter", "median3", "--tile-size", 32],
        {"eps": 0.06, "rho": 0.1, "shape": "erf", "filter": "median3", "tile_size": 32},
    ),
}


@pytest.mark.parametrize("case", list(OPTION_CASES))
def test_fuse_options(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    object_dir: Path,
    object_scans: list[tuple[str, Scan]],
    default_grid: DenseGrid,
    bounds: list[float],
) -> None:
    """Each option reaches the engine as documented, and changes the fused volume."""
    extra, kwargs = OPTION_CASES[case]
    grid_out = tmp_path / "g.npz"
    argv = ["fuse", object_dir, "--voxel-size", H, "--bounds", *bounds, *extra]
    code, _, err = run_main([*argv, "--grid-out", grid_out, "--quiet"], capsys)
    assert code == 0, err
    assert err == ""  # --quiet: no progress bar
    grid = read_grid(grid_out)
    assert_same_grid(grid, fuse_in_process(object_scans, bounds=bounds, **kwargs))
    assert not same_grid(grid, default_grid)


def test_fuse_no_return_invalid_forgets_the_background(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], object_dir: Path, bounds: list[float]
) -> None:
    """Object views are mostly no-return background; ignoring it leaves that space unknown."""
    known = {}
    for policy in ("free", "invalid"):
        grid_out = tmp_path / f"{policy}.npz"
        argv = ["fuse", object_dir, "--voxel-size", H, "--bounds", *bounds, "--quiet"]
        assert run_main([*argv, "--no-return", policy, "--grid-out", grid_out], capsys)[0] == 0
        known[policy] = np.isfinite(read_grid(grid_out).logodds)
    assert known["invalid"].sum() < 0.8 * known["free"].sum()
    assert not np.any(known["invalid"] & ~known["free"])


def test_fuse_closed_mode(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    object_dir: Path,
    object_scans: list[tuple[str, Scan]],
) -> None:
    """Closed mode fills the region of interest; its result does not depend on the tile size."""
    box = [-1.0, -1.0, -1.0, 1.0, 1.0, 1.0]
    grids = {}
    for mode, tile in (("closed", 16), ("closed", 8), ("mapping", 16)):
        grid_out = tmp_path / f"{mode}{tile}.npz"
        argv = ["fuse", object_dir, "--voxel-size", H, "--bounds", *box, "--quiet"]
        argv += ["--mode", mode, "--tile-size", tile, "--grid-out", grid_out]
        code, _, err = run_main(argv, capsys)
        assert code == 0, err
        grids[mode, tile] = read_grid(grid_out)
    closed = grids["closed", 16]
    assert closed.logodds.shape == (50, 50, 50)  # 2 m / 4 cm voxel centres per axis
    assert_same_grid(closed, fuse_in_process(object_scans, mode="closed", bounds=box))
    assert_same_grid(closed, grids["closed", 8])
    mapping = grids["mapping", 16]
    assert np.isfinite(closed.logodds).sum() > np.isfinite(mapping.logodds).sum()
    # Where mapping mode knows a voxel, closed mode gives it the same value.
    known = np.isfinite(mapping.logodds)
    assert np.array_equal(mapping.logodds[known], closed.logodds[known])


def test_fuse_closed_mode_bounds_from_the_data(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    object_dir: Path,
    object_scans: list[tuple[str, Scan]],
) -> None:
    grid_out = tmp_path / "g.npz"
    argv = ["fuse", object_dir, "--voxel-size", H, "--mode", "closed", "--grid-out", grid_out]
    code, _, err = run_main(argv, capsys)
    assert code == 0, err
    assert "closed mode: region of interest from the data:" in err
    grid = read_grid(grid_out)
    # Every measured point lies inside the grid, with room for the noise band on each side.
    points = np.concatenate([scan.points_W() for _, scan in object_scans])
    index = (points - grid.origin) / H
    eps_vox = 2.0
    assert np.all(index >= eps_vox)
    assert np.all(index <= np.array(grid.logodds.shape) - 1 - eps_vox)
    assert np.isfinite(grid.logodds).mean() > 0.95


def test_fuse_without_grid_out_writes_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], object_dir: Path
) -> None:
    before = sorted(p.relative_to(object_dir) for p in object_dir.rglob("*"))
    code, out, _ = run_main(["fuse", object_dir, "--voxel-size", H, "--quiet"], capsys)
    assert code == 0
    assert f"fused {VIEWS} scans" in out and "wrote" not in out
    assert sorted(p.relative_to(object_dir) for p in object_dir.rglob("*")) == before


# --- fuse: error exits ------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bad_datasets(
    tmp_path_factory: pytest.TempPathFactory, object_dir: Path, object_data: SyntheticDataset
) -> dict[str, Path]:
    """Copies of the object dataset, each broken in one way."""
    root = tmp_path_factory.mktemp("bad")
    sensor, scans = _dataset_parts(object_dir)
    broken = write_dataset(root / "broken", sensor, scans)
    data = (broken / "scans" / "scan_0002.npz").read_bytes()
    (broken / "scans" / "scan_0002.npz").write_bytes(data[: len(data) // 2])
    intscan = write_dataset(root / "intscan", sensor, scans)
    with (intscan / "scans" / "scan_0000.npz").open("wb") as fh:
        np.savez(fh, range=np.ones((480, 640), np.int16), pose=np.eye(4))
    badsensor = write_dataset(root / "badsensor", sensor, scans)
    meta = json.loads((badsensor / "sensor.json").read_text())
    (badsensor / "sensor.json").write_text(json.dumps({**meta, "model": "fisheye"}))
    # Every pixel a no-return: nothing to derive a closed-mode region of interest from.
    blank = np.full(sensor.shape, np.inf, np.float32)
    nopoints = write_dataset(
        root / "nopoints",
        sensor,
        [(name, Scan(range_m=blank, T_W_S=s.T_W_S, sensor=sensor)) for name, s in scans],
    )
    return {"broken": broken, "intscan": intscan, "badsensor": badsensor, "nopoints": nopoints}


# Each parameter's invalid values, refused naming the option: tests/test_params.py.
FUSE_ERRORS: dict[str, tuple[list[str], str]] = {
    "missing dataset": (["{tmp}/missing"], "missing: no such dataset folder"),
    "dataset is a file": (["{tmp}/file.txt"], "file.txt: not a directory"),
    "empty folder": (["{tmp}/empty"], "no scans/ folder"),
    "voxel size 0": (["{data}", "--voxel-size", "0"], "--voxel-size: must be a positive number"),
    "voxel size abc": (["{data}", "--voxel-size", "abc"], "--voxel-size: not a number: 'abc'"),
    "voxel size huge": (["{data}", "--voxel-size", "1000"], "--voxel-size: 1000.0 m is not"),
    "voxel size missing": (["{data}"], "the following arguments are required: --voxel-size"),
    "rho 0.7": (["{data}", "--rho", "0.7"], "--rho: outlier probability must be in (0, 1/2)"),
    "eps-per-m 1": (["{data}", "--eps-per-m", "1"], "--eps-per-m: must be in [0, 1)"),
    "falloff -1": (["{data}", "--falloff=-1"], "--falloff: must be a positive number"),
    "tile size 2": (["{data}", "--tile-size", "2"], "--tile-size: must be between 4 and 128"),
    "bounds x0 >= x1": (
        ["{data}", "--bounds", "1", "0", "0", "1", "1", "1"],
        "bounds: x0 must be less than x1",
    ),
    "bounds z0 > z1": (
        ["{data}", "--bounds", "0", "0", "2", "1", "1", "1"],
        "bounds: z0 must be less than z1",
    ),
    "bounds five numbers": (["{data}", "--bounds", "0", "0", "0", "1", "1"], "--bounds"),
    "bounds inf": (
        ["{data}", "--bounds", "0", "0", "0", "inf", "1", "1"],
        "--bounds: must be finite",
    ),
    "bounds between voxel centres": (
        ["{data}", "--bounds", "0.001", "0", "0", "0.002", "1", "1"],
        "bounds: the box holds no voxel centre",
    ),
    "bounds too large": (
        ["{data}", "--bounds", "-50", "-50", "-50", "50", "50", "50", "--grid-out", "{out}"],
        "is too large; give smaller bounds",
    ),
    "unknown filter": (["{data}", "--filter", "gauss"], "--filter: invalid choice: 'gauss'"),
    "unknown mode": (["{data}", "--mode", "open"], "--mode: invalid choice: 'open'"),
    "max-discontinuity 0": (
        ["{data}", "--max-discontinuity", "0"],
        "--max-discontinuity: must be a positive number",
    ),
    "closed without points": (
        ["{nopoints}", "--mode", "closed", "--grid-out", "{out}"],
        "closed mode: no scan has a measured point; give --bounds",
    ),
    "grid-out is a folder": (["{data}", "--grid-out", "{tmp}"], "--grid-out"),
    "grid-out under a file": (
        ["{data}", "--grid-out", "{tmp}/file.txt/g.npz"],
        "file.txt is not a directory",
    ),
    "grid-out unwritable": (["{data}", "--grid-out", "/proc/g.npz"], "cannot write in /proc"),
    "corrupted scan": (["{broken}"], "scan_0002.npz: not a readable .npz file"),
    "scan with int ranges": (["{intscan}"], "scan_0000.npz: range: must be a floating-point"),
    "unknown sensor model": (["{badsensor}"], "sensor.json: sensor.model: unknown sensor model"),
}


@pytest.mark.parametrize("case", list(FUSE_ERRORS))
def test_fuse_errors(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    case: str,
    object_dir: Path,
    bad_datasets: dict[str, Path],
) -> None:
    """Exit status 2, a message naming the problem, no traceback and no output file."""
    args, message = FUSE_ERRORS[case]
    if "/proc/" in " ".join(args) and not Path("/proc/self").exists():
        pytest.skip("needs Linux /proc as an unwritable folder")
    (tmp_path / "file.txt").write_text("x")
    (tmp_path / "empty").mkdir()
    grid_out = tmp_path / "grid.npz"
    places = {"tmp": tmp_path, "data": object_dir, "out": grid_out, **bad_datasets}
    argv = ["fuse", *(a.format(**places) for a in args)]
    if "--voxel-size" not in " ".join(argv) and case != "voxel size missing":
        argv += ["--voxel-size", str(H)]
    if "--grid-out" not in argv:
        argv += ["--grid-out", str(grid_out)]
    argv.append("--quiet")
    entries_before = sorted(p.name for p in tmp_path.iterdir())
    code, out, err = run_main(argv, capsys)
    assert code == 2, (out, err)
    assert message in err, err
    assert "Traceback" not in err
    assert not grid_out.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == entries_before
    assert no_leftovers(tmp_path) == []
    if case.startswith("grid-out"):
        assert "fused" not in out  # refused before any work


def test_grid_out_is_a_folder_names_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], object_dir: Path
) -> None:
    argv = ["fuse", object_dir, "--voxel-size", H, "--grid-out", tmp_path, "--quiet"]
    code, _, err = run_main(argv, capsys)
    assert code == 2
    assert f"rangefuse fuse: error: --grid-out {tmp_path}: is a directory" in err


# --- the progress bar -------------------------------------------------------------------------


def test_progress_bar() -> None:
    stream = io.StringIO()
    bar = ProgressBar("fuse", stream=stream, width=10)
    bar(0, 4)
    bar(2, 4)
    bar(4, 4)
    bar.close()
    bar.close()  # a second close adds nothing
    text = stream.getvalue()
    lines = text.split("\r")[1:]
    assert len(lines) == 3
    assert lines[1].startswith("fuse [#####.....] 2/4 scans")
    assert lines[2].startswith("fuse [##########] 4/4 scans")
    assert text.endswith("\n") and text.count("\n") == 1
    quiet = io.StringIO()
    off = ProgressBar("fuse", stream=quiet, enabled=False)
    off(1, 2)
    off.close()
    assert quiet.getvalue() == ""
    empty = io.StringIO()
    nothing = ProgressBar("fuse", stream=empty, width=4)
    nothing(0, 0)  # an empty dataset is complete
    assert "[####] 0/0" in empty.getvalue()
