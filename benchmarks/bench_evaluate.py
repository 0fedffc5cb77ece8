"""Benchmark the evaluate stage: wall time of ``python -m generalist_control.evaluate``.

Run: ``python benchmarks/bench_evaluate.py --policy models/policy.ckpt [--repeats 3]
[--baseline main]``. Each repeat runs the whole stage in a fresh process (every scenario of
``conf/evaluation/default.yaml``, the set-point check, the reports and figures, MLflow
logging into a copy of one SQLite store made beforehand, as after a training), for this tree
and then for the baseline (a git ref exported with ``git archive``; ``none``: no baseline),
so that each pair sees the same load. Prints the medians and the median of the pairs' ratios,
and writes ``benchmarks/results/evaluate.json``: every run's wall and CPU seconds (children
included), and whether the two trees' ``metrics.csv`` and ``scores.json`` are byte-identical.
Goal (issue 49): at most 12 s wall on 2 idle cores.
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

ROOT = Path(__file__).resolve().parents[1]


def _cpu() -> float:
    use = resource.getrusage(resource.RUSAGE_CHILDREN)
    return use.ru_utime + use.ru_stime


def _store(into: Path) -> Path:
    """An SQLite MLflow store with its schema, made once (outside the timing)."""
    into.mkdir(parents=True)
    db = into / "mlflow.db"
    code = f"import mlflow; mlflow.MlflowClient('sqlite:///{db}').search_experiments()"
    subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
    return db


def run_stage(tree: Path, policy: Path, work: Path) -> dict[str, float]:
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


def _baseline(ref: str, into: Path) -> Path:
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", ref], capture_output=True,
                             check=True).stdout  # fmt: skip
    into.mkdir(parents=True)
    subprocess.run(["tar", "-x", "-C", str(into)], input=archive, check=True)
    return into


def measure(policy: Path, baseline: str, repeats: int) -> dict[str, Any]:
    """Pairs of runs (this tree, then the baseline); their times; whether outputs match."""
    with tempfile.TemporaryDirectory() as tmp:
        trees = {"new": ROOT}
        if baseline != "none":
            trees["baseline"] = _baseline(baseline, Path(tmp) / "baseline")
        store = _store(Path(tmp) / "store")
        runs: dict[str, list[dict[str, float]]] = {name: [] for name in trees}
        for i in range(repeats):
            for name, tree in trees.items():
                work = Path(tmp) / f"{name}-{i}"
                work.mkdir()
                shutil.copyfile(store, work / "mlflow.db")
                runs[name].append(run_stage(tree, policy, work))
                r = runs[name][-1]
                print(f"run {i + 1} {name}: {r['wall_s']:.2f} s wall, {r['cpu_s']:.2f} s CPU",
                      flush=True)  # fmt: skip
        same = {
            f: len({(Path(tmp) / f"{n}-{repeats - 1}" / "eval" / f).read_bytes() for n in trees})
            == 1
            for f in ("metrics.csv", "scores.json")
        }
    out: dict[str, Any] = {}
    for name, rs in runs.items():
        out[name] = {
            "median_wall_s": statistics.median(r["wall_s"] for r in rs),
            "median_cpu_s": statistics.median(r["cpu_s"] for r in rs),
            "runs": rs,
        }
    if "baseline" in runs:
        new, base = runs["new"], runs["baseline"]
        pairs = [b["wall_s"] / n["wall_s"] for n, b in zip(new, base, strict=True)]
        out["median_pair_ratio_baseline_over_new"] = statistics.median(pairs)
        out["identical_to_baseline"] = same
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--policy", default=str(ROOT / "models" / "policy.ckpt"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--baseline", default="main", help="git ref, or 'none'")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "evaluate.json"))
    args = ap.parse_args()
    policy = Path(args.policy).resolve()
    if not policy.is_file():
        sys.exit(f"no policy at {policy}: train one (python train.py) or pass --policy")
    load_before = os.getloadavg()
    result: dict[str, Any] = {
        "benchmark": "python -m generalist_control.evaluate (default suite, 25 plants)",
        "policy": str(policy.relative_to(ROOT)) if policy.is_relative_to(ROOT) else policy.name,
        "repeats": args.repeats,
        "cores": os.cpu_count(),
        "baseline_ref": None if args.baseline == "none" else args.baseline,
        **measure(policy, args.baseline, args.repeats),
        "load_average_before_after": [load_before, os.getloadavg()],
    }
    for name in ("new", "baseline"):
        if name in result:
            r = result[name]
            print(f"{name}: median {r['median_wall_s']:.2f} s wall, {r['median_cpu_s']:.2f} s CPU")
    if "identical_to_baseline" in result:
        print(f"baseline/new, median of the pairs: "
              f"{result['median_pair_ratio_baseline_over_new']:.3f}; outputs identical: "
              f"{result['identical_to_baseline']}")  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(f"written {out}")


if __name__ == "__main__":
    main()
