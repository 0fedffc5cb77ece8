"""benchmarks/bench_families.py: a smoke run's JSON (nothing here times anything)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_a_smoke_run_writes_its_figures(tmp_path):
    out = tmp_path / "families.json"
    cmd = [sys.executable, str(REPO / "benchmarks" / "bench_families.py"), "--count", "20",
           "--repeats", "1", "--data", "--out", str(out), "families.count=20"]  # fmt: skip
    env = {**os.environ, "TMPDIR": str(tmp_path)}
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    result = json.loads(out.read_text())
    draw, parts, data = result["draw"], result["parts"], result["data"]
    assert draw["plants"] == draw["distinct_plants"] == 20 == draw["counts"]["kept"]
    assert parts["candidates"] == draw["counts"]["candidates"] >= 20
    assert data["plants"] == 20 and data["trajectories"] == 40 and data["mb_total"] > 0
    assert "20 plants (20 distinct)" in proc.stdout and f"wrote {out}" in proc.stdout
