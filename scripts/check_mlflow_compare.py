#!/usr/bin/env python
"""Check MLflow's Compare view of an ablation in a real browser (headless Chromium).

Writes a small SQLite store of fake ablation runs, laid out as the DVC ablation logs them
(experiment ``generalist-control/ablation``, the group parent ``ablation:default``, one child
per point with its params ``model.hidden``, ``experts``, ``n_parameters``, ``seed``, the
closed-loop scores ``closed_loop/mse/<plant>`` and the evaluation's verdicts
``eval/bar/<verdict>``), starts ``mlflow server`` on 127.0.0.1, opens the page that the UI's
*Compare* button opens for the children, and checks that the rendered page shows d, M, the
parameter count and a closed-loop score side by side. It saves a screenshot.

    python scripts/check_mlflow_compare.py                 # exit status 0: the view is right
    python scripts/check_mlflow_compare.py --out /tmp/cmp  # keep the store, DOM, screenshot

Needs Chromium (Debian: ``apt-get install -y chromium``) and a free local port; nothing
leaves the machine. ``tests/test_mlflow_compare.py`` checks the same runs through MLflow's
REST API (what the page reads) on every test run; this script is the check in a browser,
too heavy for the test suite (Chromium, ~30 s). Measured on 2026-12-05: see docs/sweeps.md.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.parse
import urllib.request
from contextlib import contextmanager
from pathlib import Path

import mlflow

EXPERIMENT = "generalist-control/ablation"
GROUP = "ablation:default"
#: run name -> (d, M, seed, n_parameters, closed-loop MSE on crazyflie_altitude, bar passed)
POINTS = {
    "default-d16": (16, 3, 42, 14_604, 1.35e-6, 6),
    "default-d32": (32, 3, 42, 55_308, 5.9e-8, 6),
    "default-m5": (32, 5, 42, 62_164, 4.1e-8, 5),
}
#: What the Compare page must show (params and metric names, and a value of each run).
EXPECTED = (
    "model.hidden", "experts", "n_parameters", "closed_loop/mse/crazyflie_altitude",
    "eval/bar_passed", "eval/bar/stable_everywhere",
)  # fmt: skip
CHROMIUM_FLAGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--hide-scrollbars", "--window-size=1600,2600",
)  # fmt: skip


def fake_store(uri: str, artifacts: Path) -> tuple[str, str, dict[str, str]]:
    """The fake ablation in ``uri``: (experiment id, parent run id, {run name: run id})."""
    client = mlflow.MlflowClient(uri)
    exp_id = client.create_experiment(EXPERIMENT, artifact_location=artifacts.as_uri())
    parent = client.create_run(exp_id, run_name=GROUP, tags={"gc.role": "group", "sweep": GROUP})
    client.set_terminated(parent.info.run_id)
    ids = {}
    for name, (d, m, seed, n_par, mse, passed) in POINTS.items():
        tags = {"mlflow.parentRunId": parent.info.run_id, "sweep": GROUP}
        run = client.create_run(exp_id, run_name=name, tags=tags)
        run_id = run.info.run_id
        params = {"model.hidden": d, "experts": m, "seed": seed, "n_parameters": n_par}
        for key, value in params.items():
            client.log_param(run_id, key, str(value))
        metrics = {
            "closed_loop/mse/crazyflie_altitude": mse,
            "eval/bar_passed": passed,
            "eval/bar_checked": 6,
            "eval/bar/stable_everywhere": 1.0,
            "eval/step/worst_ISE_ratio": 1.0 + mse * 1e4,
        }
        for key, value in metrics.items():
            client.log_metric(run_id, key, float(value))
        client.set_terminated(run_id)
        ids[name] = run_id
    return exp_id, parent.info.run_id, ids


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@contextmanager
def mlflow_server(uri: str, artifacts: Path, port: int, log: Path):
    """``mlflow server`` on 127.0.0.1:<port> over the store, until the block ends."""
    cmd = [
        sys.executable, "-m", "mlflow", "server", "--backend-store-uri", uri,
        "--default-artifact-root", artifacts.as_uri(), "--host", "127.0.0.1",
        "--port", str(port), "--workers", "1",
    ]  # fmt: skip
    # MLflow 3's GenAI job runner (huey consumers, seven processes) serves no compare view
    env = {**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}
    with log.open("w") as out:
        proc = subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT, env=env)
    try:
        base = f"http://127.0.0.1:{port}"
        deadline = time.monotonic() + 120
        while True:
            try:
                with urllib.request.urlopen(f"{base}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"mlflow server did not start: {log.read_text()[-2000:]}")
            time.sleep(0.5)
        yield base
    finally:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()


def compare_url(base: str, exp_id: str, run_ids: list[str]) -> str:
    """The page that the UI's Compare button opens for ``run_ids``."""
    query = urllib.parse.urlencode(
        {"runs": json.dumps(run_ids), "experiments": json.dumps([exp_id])}
    )
    return f"{base}/#/compare-runs?{query}"


def search_children(base: str, exp_id: str, parent_id: str) -> list[dict]:
    """The parent's children through the REST API (``runs/search``), as the UI reads them."""
    body = json.dumps(
        {"experiment_ids": [exp_id], "filter": f"tags.mlflow.parentRunId = '{parent_id}'"}
    ).encode()
    req = urllib.request.Request(
        f"{base}/api/2.0/mlflow/runs/search", body, {"Content-Type": "application/json"}
    )
    with urllib.request.urlopen(req, timeout=30) as r:
        return list(json.load(r).get("runs", []))


def chromium() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(name):
            return str(shutil.which(name))
    raise SystemExit("no Chromium: apt-get install -y chromium (Debian)")


def render(url: str, out: Path) -> str:
    """Headless Chromium: the page's DOM after its scripts ran; a screenshot beside it."""
    profile = out / "chromium-profile"
    flags = [*CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=30000"]
    browser = chromium()
    shot = out / "compare.png"
    subprocess.run([browser, *flags, f"--screenshot={shot}", url], capture_output=True,
                   timeout=180, check=False)  # fmt: skip
    dom = subprocess.run([browser, *flags, "--dump-dom", url], capture_output=True,
                         text=True, timeout=180, check=True).stdout  # fmt: skip
    (out / "compare.html").write_text(dom)
    return dom


def check(dom: str) -> list[str]:
    """What the page lacks: the names of :data:`EXPECTED`, each run's name and its d."""
    missing = [name for name in EXPECTED if name not in dom]
    missing += [run for run in POINTS if run not in dom]
    missing += [f"d={d} ({run})" for run, (d, *_) in POINTS.items() if f">{d}<" not in dom]
    return missing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="keep everything here")
    args = parser.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="gc-compare-"))
    out.mkdir(parents=True, exist_ok=True)
    uri = f"sqlite:///{out / 'mlflow.db'}"
    exp_id, parent_id, ids = fake_store(uri, out / "artifacts")
    with mlflow_server(uri, out / "artifacts", free_port(), out / "server.log") as base:
        rest = search_children(base, exp_id, parent_id)
        url = compare_url(base, exp_id, list(ids.values()))
        print(f"REST: {len(rest)} children of {GROUP}; compare page: {url}")
        dom = render(url, out)
    missing = check(dom)
    print(
        f"DOM: {len(dom):,} characters ({out / 'compare.html'}); screenshot {out / 'compare.png'}"
    )
    if missing:
        print("the Compare page lacks: " + ", ".join(missing))
        return 1
    print("the Compare page shows d, M, the parameters and the closed-loop score of every run")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
