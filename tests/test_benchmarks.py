"""Smoke runs of the benchmarks on tiny inputs (STYLE.md 21): they run and print a table.

They are not timed tests: the numbers are for the closing notes, not for assertions.
"""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "benchmarks"


def _run(script: str, *args: str) -> str:
    out = subprocess.run(
        [sys.executable, str(BENCH / script), *args], capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def _warm_kernels() -> None:
    # `rangefuse warmup` on its own, before a benchmark that runs it first: from an empty
    # numba cache it compiles every kernel (679 s on the 2-core machine on 2026-12-06, 579 s
    # in a CI run), which the benchmark's 600 s guard against a hang must not include
    out = subprocess.run(
        [str(Path(sys.executable).with_name("rangefuse")), "warmup"],
        capture_output=True, text=True, timeout=2400,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]


@pytest.mark.slow
def test_fusion_benchmark_smoke():
    out = _run("fusion.py", "--quick", "--modes", "mapping")
    assert "frames/s" in out and "mapping" in out


@pytest.mark.slow
def test_meshing_benchmark_smoke():
    out = _run("meshing.py", "--quick")
    assert "rangefuse refined" in out and "skimage (dense)" in out


@pytest.mark.slow
def test_out_of_core_benchmark_smoke(tmp_path):
    _warm_kernels()
    out = _run("out_of_core.py", "--quick", "--tmp", str(tmp_path))
    assert "speed-up over in-process: local cluster of 2 workers" in out
    assert "on the external cluster: True" in out


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("open3d") is None, reason="needs the bench extra")
def test_vs_open3d_benchmark_smoke():
    out = _run("vs_open3d.py", "--quick", "--rounds", "2")
    rounds = [line.split() for line in out.splitlines() if line.startswith(" 0.040 ")]
    assert [int(fields[1]) for fields in rounds] == [1, 2]
    ratios = [float(fields[7]) for fields in rounds]
    summary = next(line for line in out.splitlines() if "median ratio" in line)
    median = float(summary.split("median ratio ")[1].split()[0])
    assert abs(median - sum(ratios) / 2) <= 0.011  # of two rounds: their mean, rounded
    assert "over 2 round(s)" in summary


def test_file_creation_benchmark_smoke(tmp_path):
    out = _run("file_creation.py", str(tmp_path), "--files", "30")
    (row,) = [line.split() for line in out.splitlines() if line.startswith(str(tmp_path))]
    assert int(row[1]) == 30 and float(row[2]) > 0
    assert list(tmp_path.iterdir()) == []  # its files are removed
    bad = subprocess.run(
        [sys.executable, str(BENCH / "file_creation.py"), str(tmp_path / "nope")],
        capture_output=True, text=True,
    )  # fmt: skip
    assert bad.returncode != 0 and "not a folder" in bad.stderr
