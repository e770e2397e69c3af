"""What creating a chunk file costs on a file system (docs/lidar.md, "The store at LiDAR rates").

A store writes each tile it changes as a file of its own: staged as a temporary file and a
rename, then renamed over the committed chunk. On some file systems creating a file is the
store's main cost (an ext4 without a journal scans past every inode freed in the last
seconds or minutes). This writes ``--files`` chunk-sized files (3 per folder, as a street's
tiles spread over columns) the way the staging does, in each folder given, and prints the
time and the system time per file.

    python benchmarks/file_creation.py /var/tmp /mnt/scratch
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
import uuid
from pathlib import Path

#: Bytes of one file: a 16^3 tile of a fused street after zstd, roughly.
PAYLOAD = b"x" * 3000
PER_FOLDER = 3


def _create(root: str, n: int) -> None:
    for f in range(n // PER_FOLDER):
        folder = f"{root}/c/{f // 20}/{f % 20}"
        os.makedirs(folder, exist_ok=True)
        for k in range(PER_FOLDER):
            path = f"{folder}/{k}"
            tmp = f"{path}.{uuid.uuid4().hex}.partial"
            with open(tmp, "wb") as fh:
                fh.write(PAYLOAD)
            os.replace(tmp, path)


def measure(where: Path, n: int) -> tuple[float, float]:
    """Seconds and system seconds per file, creating ``n`` files under ``where``."""
    with tempfile.TemporaryDirectory(dir=where) as root:
        c0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        _create(root, n)
        seconds = time.perf_counter() - t0
        c1 = resource.getrusage(resource.RUSAGE_SELF)
        shutil.rmtree(root, ignore_errors=True)
    return seconds / n, (c1.ru_stime - c0.ru_stime) / n


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", nargs="+", type=Path, help="folders on the file systems")
    parser.add_argument("--files", type=int, default=6000, help="files per folder (default 6000)")
    args = parser.parse_args()
    if args.files < PER_FOLDER:
        raise SystemExit(f"--files: give at least {PER_FOLDER}, got {args.files}")
    for folder in args.folders:
        if not folder.is_dir():
            raise SystemExit(f"{folder}: not a folder")
    print(f"{'folder':<30} {'files':>7} {'ms/file':>8} {'sys ms/file':>12} {'files/s':>8}")
    for folder in args.folders:
        per_file, sys_per_file = measure(folder, args.files)
        print(f"{folder!s:<30} {args.files:>7} {1000 * per_file:>8.3f} "
              f"{1000 * sys_per_file:>12.3f} {1 / per_file:>8.0f}")  # fmt: skip


if __name__ == "__main__":
    main()
