"""The family policy's training time: the whole training command, timed (issue 50).

    python benchmarks/bench_train_family.py [--experiment family_card] [--threads 2]
        [--families data/families/default] [--limit SECONDS] [overrides ...]

Runs ``python -m generalist_control.train experiment=<experiment>`` over the family's
demonstrations and the 20 catalogue plants the held-out protocol trains on (its five
``held_out`` plants left out), in a fresh folder (run, models and MLflow store under a
temporary directory), and reports the command's wall time, its epochs, the windows it
trained on, the peak resident memory of the training process and the machine's load
average before and after (a figure under load says so). Issue 50's bar: at most 30 min on
2 cores, idle. With ``--limit`` a training still running then is stopped and the wall time
is a lower bound (``stopped_at_limit``). Writes ``benchmarks/results/train_family.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "benchmarks" / "results" / "train_family.json"
BAR_S = 30 * 60.0


def _held_out() -> list[str]:
    return [
        str(h) for h in yaml.safe_load((REPO / "conf" / "unseen.yaml").read_text())["held_out"]
    ]


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--experiment", default="family_card", help="the family recipe to time")
    p.add_argument("--threads", type=int, default=2, help="torch CPU threads of the training")
    p.add_argument("--families", default="data/families/default", help="the family's data")
    p.add_argument("--out", type=Path, default=RESULTS)
    p.add_argument("--models", type=Path, default=None, help="keep the policy here (default: not)")
    p.add_argument("--limit", type=float, default=None, help="stop the training after this many s")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. trainer.max_epochs=2")
    args = p.parse_args(argv)
    # stopped, the training stops too: subprocess.run kills it on the exception
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    with tempfile.TemporaryDirectory(prefix="bench_family_") as tmp:
        cmd = [
            sys.executable, "-m", "generalist_control.train", f"experiment={args.experiment}",
            f"threads={args.threads}", f"train_families.dirs=[{args.families}]",
            f"held_out=[{','.join(_held_out())}]", f"run_dir={tmp}/run",
            f"paths.models_dir={args.models or Path(tmp) / 'models'}",
            f"logger.tracking_uri=sqlite:///{tmp}/mlflow.db",
            f"logger.artifact_location={tmp}/mlruns", "logger.log_model=false",
            "trainer.enable_progress_bar=false", *args.overrides,
        ]  # fmt: skip
        load = os.getloadavg()
        start = time.perf_counter()
        try:
            proc = subprocess.run(
                cmd, cwd=REPO, capture_output=True, text=True, timeout=args.limit
            )
        except subprocess.TimeoutExpired:  # over the limit: the figure is a lower bound
            proc, metrics = None, {}
        wall = time.perf_counter() - start
        if proc is not None and proc.returncode != 0:
            sys.stderr.write(proc.stderr[-4000:])
            raise SystemExit(f"the training failed (exit {proc.returncode})")
        if proc is not None:
            metrics = json.loads(
                (args.models or Path(tmp) / "models").joinpath("metrics.json").read_text()
            )
    peak_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    result = {
        "experiment": args.experiment, "threads": args.threads, "families": args.families,
        "overrides": args.overrides, "wall_s": wall, "bar_s": BAR_S, "within_bar": wall <= BAR_S,
        "stopped_at_limit": proc is None,
        "epochs": metrics.get("epochs"), "peak_rss_mb": peak_mb,
        "load_before": load, "load_after": os.getloadavg(), "cpus": os.cpu_count(),
        "machine": platform.processor() or platform.machine(),
    }  # fmt: skip
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
