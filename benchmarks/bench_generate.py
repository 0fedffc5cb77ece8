"""Benchmark the data stage: wall time and peak memory for all 25 plants, written to disk.

Run: ``python benchmarks/bench_generate.py [--repeats 5]``. Each repeat runs the whole stage
(config composition, LQI designs, simulation, parquet + manifest written to a temporary
directory) in a fresh process, so peak RSS is that of one stage run. Prints the median and
writes ``benchmarks/results/generate.json``. Goals (issue 2): within 15 s on 2 cores, data
memory under 1 GB.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
import numpy as np
from hydra import compose, initialize_config_dir
from generalist_control.common.paths import conf_dir
from generalist_control.generate import run
from generalist_control.data.demos import load_demos
t_import = time.perf_counter() - t0
rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
with initialize_config_dir(str(conf_dir()), version_base="1.3"):
    cfg = compose("config", overrides=[f"paths.data_dir={sys.argv[1]}"])
t1 = time.perf_counter()
manifest = run(cfg)
t_stage = time.perf_counter() - t1
t2 = time.perf_counter()
demos, _ = load_demos(sys.argv[1])
t3 = time.perf_counter()
w = demos.windows(manifest["history"], manifest["horizon"])
t_windows = time.perf_counter() - t3
arrays = [w.state, w.mask, w.ref, w.tag, w.target, w.traj]
print(json.dumps({
    "import_s": t_import, "stage_s": t_stage,
    "load_and_window_s": time.perf_counter() - t2, "windows_s": t_windows,
    "n_demonstrations": manifest["n_demonstrations"], "n_windows_built": len(w),
    "window_bytes": int(sum(a.nbytes for a in arrays)),
    "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    "baseline_rss_mb": rss0 / 1024,
}))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "generate.json"))
    args = ap.parse_args()
    runs = []
    for i in range(args.repeats):
        with tempfile.TemporaryDirectory() as tmp:
            proc = subprocess.run(
                [sys.executable, "-c", CHILD, str(Path(tmp) / "demos")],
                capture_output=True,
                text=True,
                check=True,
            )
        runs.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        print(
            f"run {i + 1}: stage {runs[-1]['stage_s']:.2f} s, peak RSS "
            f"{runs[-1]['peak_rss_mb']:.0f} MB",
            flush=True,
        )
    med = lambda k: statistics.median(r[k] for r in runs)  # noqa: E731
    result = {
        "benchmark": "generate (25 plants, default config)",
        "repeats": args.repeats,
        "median_stage_s": med("stage_s"),
        "median_import_s": med("import_s"),
        "median_stage_plus_import_s": med("stage_s") + med("import_s"),
        "median_load_and_window_s": med("load_and_window_s"),
        "n_demonstrations": runs[0]["n_demonstrations"],
        "window_arrays_mb": runs[0]["window_bytes"] / 2**20,
        "median_peak_rss_mb": med("peak_rss_mb"),
        "median_baseline_rss_mb": med("baseline_rss_mb"),
        "goal_stage_s": 15.0,
        "goal_data_memory_mb": 1024,
        "runs": runs,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(
        f"median stage (write to disk): {result['median_stage_s']:.2f} s "
        f"(+ {result['median_import_s']:.2f} s imports), goal 15 s"
    )
    print(
        f"load + build {result['n_demonstrations']} windows: "
        f"{result['median_load_and_window_s']:.2f} s; window arrays "
        f"{result['window_arrays_mb']:.0f} MB; peak RSS {result['median_peak_rss_mb']:.0f} MB "
        f"(of which {result['median_baseline_rss_mb']:.0f} MB is the imported libraries)"
    )
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
