"""The command line in a new user's first hour (issue 20, part 4): ``--version``, help on
every argument, a quick ``--help`` (no heavy module imported), outputs in missing folders
refused, negative numbers with exponents as values, progress bars with an estimate of the
time left, and a note when kernels are compiled."""

from __future__ import annotations

import argparse
import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rangefuse.service import _progress
from rangefuse.service._progress import ProgressBar, format_seconds, note
from rangefuse.service.cli import _COMMANDS, build_parser, main
from rangefuse.service.warmup import COMPILING, announce_compilation

from tests.test_cli import run_main, run_subprocess

#: Modules that ``rangefuse --help`` must not import (each costs a tenth of a second or more).
HEAVY = ("numpy", "numba", "zarr", "fastapi", "trimesh", "dask", "distributed", "uvicorn",
         "pydantic", "scipy", "rangefuse.engine", "rangefuse.storage")  # fmt: skip


def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every (sub)command's parser by its words, ``token create`` included."""
    found = {}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                found[name] = sub
                for inner, deeper in _subparsers(sub).items():
                    found[f"{name} {inner}"] = deeper
    return found


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    from importlib.metadata import version

    code, out, _ = run_main(["--version"], capsys)
    assert code == 0
    assert out.strip() == f"rangefuse {version('rangefuse')}"


def test_every_argument_has_help() -> None:
    parsers = _subparsers(build_parser())
    assert set(_COMMANDS) <= set(parsers)
    assert {"token create", "token list", "token revoke"} <= set(parsers)
    missing = []
    for words, parser in parsers.items():
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                continue
            if not (action.help or "").strip() or action.help == argparse.SUPPRESS:
                missing.append(f"{words}: {action.dest}")
    assert missing == []


def test_every_command_help_shows_its_positional_arguments(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, out, _ = run_main(["fuse", "--help"], capsys)
    assert code == 0
    assert "DATASET" in out and "dataset folder (sensor.json and scans/*.npz" in out
    code, out, _ = run_main(["synth", "--help"], capsys)
    assert "SCENE" in out and "object (a robot arm" in out
    code, out, _ = run_main(["--help"], capsys)
    assert code == 0
    for name, (help_text, _, _) in _COMMANDS.items():
        assert name in out
        assert help_text.split()[0] in out


def test_help_imports_no_heavy_module() -> None:
    """``rangefuse --help``, ``--version`` and a light command's help load only the standard
    library and the command line's own modules (the start-up time is in README.md)."""
    script = (
        "import sys\n"
        "from rangefuse.service.cli import main\n"
        "for argv in (['--help'], ['--version'], ['warmup', '--help'], ['serve', '--help']):\n"
        "    try:\n"
        "        main(argv)\n"
        "    except SystemExit:\n"
        "        pass\n"
        f"heavy = [m for m in {HEAVY!r} if m in sys.modules]\n"
        "print('HEAVY', heavy, file=sys.stderr)\n"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60, check=False
    )
    assert proc.returncode == 0, proc.stderr
    assert "HEAVY []" in proc.stderr, proc.stderr


def test_unknown_command_and_missing_command(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(["fusee"], capsys)
    assert code == 2 and "invalid choice: 'fusee'" in err
    code, _, err = run_main([], capsys)
    assert code == 2 and "required: COMMAND" in err


@pytest.mark.parametrize("option", ["-o", "--grid-out"])
def test_an_output_in_a_missing_folder_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str
) -> None:
    data = tmp_path / "data"
    assert run_main(["synth", "object", data, "--views", 1, "--quiet"], capsys)[0] == 0
    target = tmp_path / "missing" / ("out.ply" if option == "-o" else "grid.npz")
    argv = ["fuse", data, "--voxel-size", 0.04, option, target, "--quiet"]
    code, out, err = run_main(argv, capsys)
    assert code == 2
    assert f"rangefuse fuse: error: {option} {target}: no folder {target.parent}" in err
    assert "fused" not in out  # refused before any work
    assert not target.parent.exists()


def test_the_console_script_refuses_a_missing_folder(tmp_path: Path) -> None:
    proc = run_subprocess("extract", tmp_path / "store", "-o", "/nonexistent-dir/out.ply")
    assert proc.returncode == 2
    assert "-o /nonexistent-dir/out.ply: no folder /nonexistent-dir" in proc.stderr
    assert not Path("/nonexistent-dir").exists()


def test_negative_bounds_with_exponents_parse(capsys: pytest.CaptureFixture[str]) -> None:
    words = ["fuse", "data", "--voxel-size", "1e-2", "--bounds", "-1e0", "-2.5E-1", "-.5", "-7",
             "1", "2e+0"]  # fmt: skip
    args = build_parser(["fuse"]).parse_args(words)
    assert args.bounds == [-1.0, -0.25, -0.5, -7.0, 1.0, 2.0]
    args = build_parser(["extract"]).parse_args(["extract", "s", "--bounds", "-1e9", "-1e9",
                                                 "-1e9", "1e9", "1e9", "1e9"])  # fmt: skip
    assert args.bounds == [-1e9, -1e9, -1e9, 1e9, 1e9, 1e9]
    # an option is still an option
    with pytest.raises(SystemExit):
        build_parser(["fuse"]).parse_args(["fuse", "data", "--bounds", "-1", "-o"])
    assert "--bounds: expected 6 arguments" in capsys.readouterr().err


def test_negative_infinite_bounds_are_refused_with_a_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["fuse", tmp_path, "--voxel-size", "0.1", "--bounds", "-inf", "0", "0", "1", "1", "1"]
    code, _, err = run_main(argv, capsys)
    assert code == 2 and "--bounds: must be finite, got '-inf'" in err


def test_progress_bar_shows_the_time_left() -> None:
    stream = io.StringIO()
    bar = ProgressBar("fuse", stream=stream, width=10)
    bar.start -= 30.0  # as if the first scans had taken 30 s
    bar(0, 4)
    bar(1, 4)
    bar(4, 4)
    bar.close()
    first, one, done = stream.getvalue().split("\r")[1:]
    assert "ETA ?" in first
    assert "1/4 scans" in one and "ETA 1m30s" in one  # 30 s a scan, three left
    assert done.rstrip().endswith("done")


def test_format_seconds() -> None:
    seconds = (0, 7.4, 59.6, 125, 3725)
    assert [format_seconds(s) for s in seconds] == ["0s", "7s", "1m00s", "2m05s", "1h02m"]


def test_a_note_starts_a_line_below_the_bar() -> None:
    stream = io.StringIO()
    bar = ProgressBar("fuse", stream=stream, width=4)
    bar(1, 2)
    note("hello", stream)
    bar(2, 2)
    bar.close()
    text = stream.getvalue()
    assert "scans" in text.split("\n")[0] and text.split("\n")[1] == "hello"
    assert text.endswith("done   \n")
    assert _progress._drawn is None


def test_synth_shows_progress_bars(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, _, err = run_main(["synth", "object", tmp_path / "d", "--views", 2], capsys)
    assert code == 0
    assert "render [" in err and "2/2 scans" in err and "write [" in err and "ETA" in err
    code, _, err = run_main(["synth", "object", tmp_path / "q", "--views", 1, "--quiet"], capsys)
    assert code == 0 and err == ""


def test_a_compilation_is_announced_once(capsys: pytest.CaptureFixture[str]) -> None:
    """numba compiles only what its cache lacks: a kernel defined here has no cache, so
    calling it compiles it, and the note says so once."""
    from numba import njit

    announce_compilation()

    @njit
    def add_one(x: int) -> int:
        return x + 1

    @njit
    def double(x: int) -> int:
        return 2 * x

    assert add_one(1) == 2 and double(2) == 4
    err = capsys.readouterr().err
    assert err.count(COMPILING) == 1
    assert "rangefuse warmup" in err


def test_main_announces_compilation_for_kernel_commands(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    calls = []
    monkeypatch.setattr("rangefuse.service.warmup.announce_compilation", lambda: calls.append(1))
    assert main(["synth", "object", str(tmp_path / "d"), "--views", "1", "--quiet"]) == 0
    assert main(["info", str(tmp_path / "none")]) == 2  # a store command without kernels
    assert calls == [1]


def _make_run_line(*words: str, env: dict[str, str] | None = None) -> str:
    """The command ``make run`` would start (``make -n``; the install step left out)."""
    root = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        ["make", "-n", "-o", ".venv/.installed-dev", "run", *words],
        cwd=root,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
        env={**os.environ, **(env or {})},
    )
    (line,) = [ln for ln in proc.stdout.splitlines() if "rangefuse serve" in ln]
    return " ".join(line.split())


def test_make_run_takes_a_port_and_otherwise_leaves_it_to_the_settings() -> None:
    assert _make_run_line("PORT=8123").endswith("rangefuse serve --data-dir data --port 8123")
    assert _make_run_line("PORT=8123", "HOST=0.0.0.0").endswith(
        "serve --data-dir data --host 0.0.0.0 --port 8123"
    )
    # no PORT: no --port, so that RANGEFUSE_PORT is read (below)
    line = _make_run_line(env={"RANGEFUSE_PORT": "9123"})
    assert line.endswith("rangefuse serve --data-dir data")


def test_serve_reads_rangefuse_port(monkeypatch: pytest.MonkeyPatch) -> None:
    from rangefuse.service._serve_cli import _settings

    monkeypatch.setenv("RANGEFUSE_PORT", "9123")
    parser = build_parser(["serve"])
    assert _settings(parser.parse_args(["serve"])).port == 9123
    assert _settings(parser.parse_args(["serve", "--port", "8124"])).port == 8124
