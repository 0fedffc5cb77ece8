"""Benchmark the evaluate stage: wall time of ``python -m generalist_control.evaluate``.

Run: ``python benchmarks/bench_evaluate.py --policy models/policy.ckpt [--repeats 3]
[--baseline main] [--store existing|new]``. Each repeat runs the whole stage in a fresh
process (imports, ONNX export, every scenario of ``conf/evaluation/default.yaml``, the
set-point check, the reports and figures, MLflow logging into a temporary store), once for
this tree and once for the
baseline, a git ref exported with ``git archive`` (``--baseline none``: no baseline),
alternately, so both see the same load. Prints the medians and writes
``benchmarks/results/evaluate.json`` with every run, the CPU seconds (user + system,
children included: less sensitive to other load than wall time), the machine's load average
before and after, and how far the two trees' ``metrics.csv`` and ``summary.json`` differ.
Goal (issue 38): at most 10 s wall on 2 idle cores for the default suite.

``--store existing`` (default): each run logs into a copy of one SQLite store made before the
runs, as after a training (the stage's usual case); ``new``: into a store that does not exist
yet, so MLflow creates its schema inside the timed run (about 1.5 CPU s).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def _template_store(tree: Path, into: Path) -> Path:
    """An SQLite MLflow store with its schema, made once (outside the timing)."""
    into.mkdir(parents=True)
    db = into / "mlflow.db"
    code = ("from generalist_control.tracking.mlflow_utils import set_tracking; "
            f"set_tracking({{'tracking_uri': 'sqlite:///{db}'}})")  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(tree / "src")}
    subprocess.run([sys.executable, "-c", code], env=env, check=True, capture_output=True)
    return db


def run_stage(tree: Path, policy: Path, work: Path) -> dict[str, Any]:
    """One ``python -m generalist_control.evaluate`` of ``tree`` in ``work``: its times."""
    overrides = [
        f"policy={policy}",
        f"paths.reports_dir={work / 'eval'}",
        f"logger.tracking_uri=sqlite:///{work / 'mlflow.db'}",
        f"logger.artifact_location={work / 'mlruns'}",
        f"hydra.run.dir={work / 'hydra'}",
    ]
    env = {**os.environ, "PYTHONPATH": str(tree / "src")}
    cpu, start = _cpu(), time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "generalist_control.evaluate", *overrides],
        cwd=work, env=env, capture_output=True, text=True,
    )  # fmt: skip
    wall = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"evaluate failed in {tree}:\n{proc.stderr[-4000:]}")
    return {"wall_s": wall, "cpu_s": _cpu() - cpu}


def compare(new: Path, old: Path) -> dict[str, Any]:
    """Largest differences between two evaluations' ``metrics.csv``; equal summaries?"""
    a, b = pd.read_csv(new / "metrics.csv"), pd.read_csv(old / "metrics.csv")
    keys = ["system", "scenario", "controller", "run", "metric"]
    same_rows = len(a) == len(b) and bool((a[keys].to_numpy() == b[keys].to_numpy()).all())
    out: dict[str, Any] = {"same_rows": same_rows}
    if same_rows:
        x, y = a.value.to_numpy(), b.value.to_numpy()
        ok = np.isfinite(x) & np.isfinite(y)
        d = np.abs(x[ok] - y[ok])
        rel = d / np.maximum(np.abs(y[ok]), 1e-300)
        big = np.abs(y[ok]) >= 1e-3  # values above the float32 noise floor of a metric
        out |= {
            "same_nan": bool((np.isnan(x) == np.isnan(y)).all()),
            "exactly_equal_share": float((d == 0).mean()),
            "max_abs_diff": float(d.max()),
            "max_rel_diff": float(rel.max()),
            "max_rel_diff_values_over_1e-3": float(rel[big].max()) if big.any() else 0.0,
            "bytes_identical": (new / "metrics.csv").read_bytes()
            == (old / "metrics.csv").read_bytes(),
        }
    sa, sb = (json.loads((p / "summary.json").read_text()) for p in (new, old))
    for s in (sa, sb):
        s.pop("policy", None), s.pop("provenance", None)
    out["summary_equal"] = sa == sb
    out["quality_bar_equal"] = sa.get("quality_bar") == sb.get("quality_bar")
    return out


def _baseline(ref: str, into: Path) -> Path:
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], capture_output=True,
                             check=True).stdout  # fmt: skip
    into.mkdir(parents=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def measure(policy: Path, baseline: str, repeats: int, store: str) -> dict[str, Any]:
    """Alternate runs of this tree and the baseline; their times and how their outputs differ."""
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"new": ROOT}
        if baseline != "none":
            trees["baseline"] = _baseline(baseline, Path(tmp) / "baseline")
        template = _template_store(ROOT, Path(tmp) / "store") if store == "existing" else None
        runs: dict[str, list[dict[str, Any]]] = {name: [] for name in trees}
        for i in range(repeats):
            for name, tree in trees.items():
                work = Path(tmp) / f"{name}-{i}"
                work.mkdir()
                if template is not None:
                    shutil.copyfile(template, work / "mlflow.db")
                runs[name].append(run_stage(tree, policy, work))
                r = runs[name][-1]
                print(f"run {i + 1} {name}: {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU",
                      flush=True)  # fmt: skip
        last = Path(tmp) / f"new-{repeats - 1}" / "eval"
        old = Path(tmp) / f"baseline-{repeats - 1}" / "eval"
        diff = compare(last, old) if "baseline" in trees else None
    out: dict[str, Any] = {}
    for name, rs in runs.items():
        out[name] = {
            "median_wall_s": statistics.median(r["wall_s"] for r in rs),
            "median_cpu_s": statistics.median(r["cpu_s"] for r in rs),
            "runs": rs,
        }
    if diff is not None:
        out["speedup_wall"] = out["baseline"]["median_wall_s"] / out["new"]["median_wall_s"]
        out["metrics_vs_baseline"] = diff
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--policy", default=str(ROOT / "models" / "policy.ckpt"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default="main", help="git ref, or 'none'")
    ap.add_argument(
        "--store",
        choices=["existing", "new"],
        default="existing",
        help="log into a copy of a made store (default), or a store not made yet",
    )
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "evaluate.json"))
    args = ap.parse_args()
    policy = Path(args.policy).resolve()
    if not policy.is_file():
        sys.exit(f"no policy at {policy}: train one (python train.py) or pass --policy")
    load_before = os.getloadavg()
    measured = measure(policy, args.baseline, args.repeats, args.store)
    result: dict[str, Any] = {
        "benchmark": "python -m generalist_control.evaluate (default suite, 25 plants)",
        "policy": str(policy.relative_to(ROOT)) if policy.is_relative_to(ROOT) else policy.name,
        "repeats": args.repeats,
        "cores": os.cpu_count(),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "baseline_ref": None if args.baseline == "none" else args.baseline,
        "store": args.store,
        **measured,
    }
    for name in ("new", "baseline"):
        if name in result:
            r = result[name]
            print(f"{name}: median {r['median_wall_s']:.2f} s wall, {r['median_cpu_s']:.2f} s CPU")
    if "speedup_wall" in result:
        print(f"speed-up {result['speedup_wall']:.1f}x; metrics.csv against the baseline: "
              f"{result['metrics_vs_baseline']}")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {out}")


if __name__ == "__main__":
    main()
