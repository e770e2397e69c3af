"""Benchmark runs in child processes of their own (a fresh peak RSS for each run)."""

from __future__ import annotations

import json
import subprocess
import sys


def run_child(script: str, cfg: dict) -> dict:
    """Run ``script --child CFG`` (the configuration as JSON) in a new Python process and
    return the JSON object its last line of output prints; its stderr and exit status on a
    failure."""
    out = subprocess.run(
        [sys.executable, script, "--child", json.dumps(cfg)], capture_output=True, text=True
    )
    if out.returncode != 0:
        print(out.stderr[-3000:], file=sys.stderr)
        raise SystemExit(out.returncode)
    return json.loads(out.stdout.strip().splitlines()[-1])
