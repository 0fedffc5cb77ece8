"""The DVC `generate` stage in a throw-away git repository, and push/pull to a local remote."""

import json
import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from helpers import tiny_train_overrides

ROOT = Path(__file__).resolve().parents[1]
DVC = [sys.executable, "-m", "dvc"]


def sh(cmd, cwd, env):
    proc = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, f"{cmd}: {proc.stdout}\n{proc.stderr}"
    return proc.stdout + proc.stderr


@pytest.fixture
def repo(tmp_path):
    """A copy of the project's pipeline files in a fresh git + DVC repository."""
    work = tmp_path / "repo"
    work.mkdir()
    for item in ("src", "conf", "dvc.yaml"):
        src = ROOT / item
        if src.is_dir():
            shutil.copytree(src, work / item, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy(src, work / item)
    env = {
        **os.environ,
        "PYTHONPATH": str(work / "src"),
        "DVC_NO_ANALYTICS": "1",
        "GIT_AUTHOR_NAME": "t",
        "GIT_AUTHOR_EMAIL": "t@t",
        "GIT_COMMITTER_NAME": "t",
        "GIT_COMMITTER_EMAIL": "t@t",
    }
    env.pop("GC_CONF_DIR", None)
    sh(["git", "init", "-q"], work, env)
    sh([*DVC, "init", "-q"], work, env)
    return work, env


def test_repro_skip_rerun_push_pull(repo, tmp_path):
    work, env = repo
    out = sh([*DVC, "repro", "generate"], work, env)
    assert "Running stage 'generate'" in out
    manifest = json.loads((work / "data/demos/manifest.json").read_text())
    families = yaml.safe_load((work / "conf/data/demos.yaml").read_text())["families"]
    assert manifest["n_trajectories"] == 25 * (64 + sum(f["count"] for f in families.values()))
    assert "didn't change, skipping" in sh([*DVC, "repro", "generate"], work, env)

    # changing the amplitude grid re-runs the stage
    grid = work / "conf/data/demos.yaml"
    grid.write_text(
        grid.read_text().replace(
            "{start: 15.0, stop: 20.0, step: 5.0}", "{start: 16.0, stop: 20.0, step: 4.0}"
        )
    )
    assert "Running stage 'generate'" in sh([*DVC, "repro", "generate"], work, env)
    changed = json.loads((work / "data/demos/manifest.json").read_text())
    assert changed["content_hash"] != manifest["content_hash"]

    # push to a local directory remote, lose cache and outputs, pull them back
    remote = tmp_path / "remote"
    sh([*DVC, "remote", "add", "-f", "-d", "tmpstore", str(remote)], work, env)
    sh([*DVC, "push", "generate"], work, env)
    assert any(remote.rglob("*"))
    shutil.rmtree(work / "data/demos")
    shutil.rmtree(work / ".dvc/cache")
    sh([*DVC, "pull", "generate"], work, env)
    pulled = json.loads((work / "data/demos/manifest.json").read_text())
    assert pulled["content_hash"] == changed["content_hash"]
    assert "didn't change, skipping" in sh([*DVC, "repro", "generate"], work, env)


# --- the views of `dvc exp show`, `dvc metrics show` and the data stage's numerics ---

FAKE_TRAIN = """\
import json, yaml
h = yaml.safe_load(open("conf/model/generalist.yaml"))["hidden"]
m = json.load(open("base_metrics.json"))
out = {k: v * h / 32 if isinstance(v, float) else v for k, v in m.items()}
json.dump(out, open("models/metrics.json", "w"))
s = {"diverged": 0, "bar_passed": 6, "bar_checked": 6, "ISE_ratio": 1 + h / 1e4,
     "ITAE_ratio": 1 + h / 1e3, "RMSE_ratio": 1 + h / 1e5, "ess_ppm": 9.1 * h}
json.dump(s, open("reports/eval/scores.json", "w"))
open("models/policy.ckpt", "w").write(str(h))
"""


def _fake_pipeline(work: Path) -> None:
    """The project's ``train`` stage (params, conf deps, metrics) around a 1-second command.

    The command writes the committed ``models/metrics.json`` with every float changed and an
    evaluate-like ``scores.json``, as a real experiment changes every metric.
    """
    spec = yaml.safe_load((ROOT / "dvc.yaml").read_text())
    train, evaluate = spec["stages"]["train"], spec["stages"]["evaluate"]
    stage = {
        "cmd": "python fake_train.py",
        "deps": [d for d in train["deps"] if d.startswith("conf/")],
        "params": train["params"] + evaluate["params"] + spec["stages"]["generate"]["params"],
        "outs": ["models/policy.ckpt"],
        "metrics": train["metrics"] + evaluate["metrics"],
    }
    (work / "dvc.yaml").write_text(yaml.safe_dump({"stages": {"train": stage}}))
    (work / "fake_train.py").write_text(FAKE_TRAIN)
    shutil.copy(ROOT / "models/metrics.json", work / "base_metrics.json")
    (work / "models").mkdir(exist_ok=True)
    (work / "reports/eval").mkdir(parents=True, exist_ok=True)


def test_exp_show_only_changed_fits_120_columns(repo):
    work, env = repo
    _fake_pipeline(work)
    sh([*DVC, "repro"], work, env)
    sh(["git", "add", "-A"], work, env)
    sh(["git", "commit", "-qm", "baseline"], work, env)
    sh([*DVC, "exp", "run", "-q", "-S", "conf/model/generalist.yaml:hidden=64",
        "-S", "conf/config.yaml:experts=5"], work, env)  # fmt: skip
    assert yaml.safe_load((work / "conf/model/generalist.yaml").read_text())["hidden"] == 64
    changed = sh([*DVC, "exp", "show", "--only-changed", "--csv"], work, env)
    header = changed.splitlines()[0].split(",")
    assert {"hidden", "experts", "ISE_ratio", "ess_ppm"} <= set(header), header
    assert not {"heads", "seed", "defaults", "policy"} & set(header), header  # unchanged
    # every changed file dep is a column of its full MD5 (DVC 3.67), and every changed metric
    # a column: `make exp-show` drops the deps and the secondary metrics, as written there
    deps = yaml.safe_load((work / "dvc.yaml").read_text())["stages"]["train"]["deps"]
    metrics_json = json.loads((work / "base_metrics.json").read_text())
    make = re.search(r"--drop '(.+)'", (ROOT / "Makefile").read_text())
    assert make, "Makefile's exp-show target"
    drop = make.group(1).replace("$$", "$")
    table = sh([*DVC, "exp", "show", "--only-changed", "--no-pager", "--drop", drop],
               work, {**env, "COLUMNS": "120"})  # fmt: skip
    for column in ("hidden", "experts", "ess_ppm", "ISE_ratio", "val/log10_closed_loop"):
        assert column in table, table
    assert all(len(line) <= 120 for line in table.splitlines()), table
    assert "…" not in table, f"a column was collapsed:\n{table}"
    full = sh([*DVC, "exp", "show", "--no-pager", "--csv"], work, env).splitlines()[0]
    params = [c for c in full.split(",") if c not in metrics_json and c not in deps]
    assert len(params) <= 25, params


def test_metrics_show_reads_small_errors(repo):
    from generalist_control.evaluation.writer import headline_scores

    work, env = repo
    summary = {
        "diverged": {"GC": {}, "GC-AW": {"step": 1}},
        "ratios": {"step": {"worst_ISE_ratio": 1.001, "worst_ITAE_ratio": 1.04,
                            "worst_relative_ess_GC": 3.2e-9},
                   "random_steps": {"worst_relative_ess_GC": 2.5e-11}},
        "tracking": {"sine": {"worst_RMSE_ratio": 1.01}, "ramp": {"worst_RMSE_ratio": 1.02}},
        "quality_bar": {"a": True, "b": False, "c": None},
    }  # fmt: skip
    scores = headline_scores(summary)
    assert scores == {
        "diverged": 1,
        "bar_passed": 1,
        "bar_checked": 2,
        "ISE_ratio": 1.001,
        "ITAE_ratio": 1.04,
        "RMSE_ratio": 1.02,
        "ess_ppm": pytest.approx(3.2e-3),
    }
    (work / "dvc.yaml").write_text("metrics:\n  - scores.json\n")
    (work / "scores.json").write_text(json.dumps(scores))
    shown = sh([*DVC, "metrics", "show"], work, env)
    assert "0.0032" in shown and "1.001" in shown, shown


#: "Other machines": what a different CPU changes, OpenBLAS's kernels and numpy's SIMD loops.
MACHINES = (
    {},
    {"OPENBLAS_CORETYPE": "Sandybridge", "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL"},
    {"OPENBLAS_CORETYPE": "Nehalem", "OPENBLAS_NUM_THREADS": "2"},
)
#: Plants whose data differ between those settings (BLAS in every plant's LQI design and
#: step, numpy's sin in the sines family of mass_spring_damper), 2 s trajectories.
TINY_GENERATE = [
    "systems.include=[cstr,hydraulic_actuator,mass_spring_damper]",
    "data.duration=2.0",
    "data.amplitudes.segments=[{start:1.0,stop:20.0,step:1.0}]",
]


def _stage_cmd(stage: str) -> str:
    """``stage``'s command in dvc.yaml."""
    return yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"][stage]["cmd"]


def _generate(cmd: str, machine: dict[str, str], out: Path) -> tuple[str, str]:
    """Run ``cmd`` (a shell command) on the tiny config under ``machine``'s settings."""
    env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), **machine}
    args = [*TINY_GENERATE, f"paths.data_dir={out}", f"hydra.run.dir={out.parent / 'hydra'}"]
    full = f"{cmd} {' '.join(shlex.quote(a) for a in args)}"
    proc = subprocess.run(["bash", "-c", full], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = (out / "trajectories.parquet").read_bytes()
    return json.loads((out / "manifest.json").read_text())["content_hash"], data.hex()


@pytest.mark.slow  # six small generations, ~90 s
def test_data_stage_bytes_do_not_depend_on_the_cpu(tmp_path):
    stage_cmd = _stage_cmd("generate")
    assert stage_cmd.endswith("python -m generalist_control.generate")
    plain = "python -m generalist_control.generate"
    # unpinned, the emulated machines disagree: the emulation reproduces the issue
    unpinned = {_generate(plain, m, tmp_path / f"u{i}" / "demos") for i, m in enumerate(MACHINES)}
    assert len(unpinned) == len(MACHINES)
    # the stage's command gives the same hash and bytes on every one
    pinned = {
        _generate(stage_cmd, m, tmp_path / f"p{i}" / "demos") for i, m in enumerate(MACHINES)
    }
    assert len(pinned) == 1


#: What a different CPU changes in training: ATen's vectorised kernels, MKL's code branch and
#: oneDNN's instruction set (the LSTM), each set here as another machine would pick it.
TORCH_MACHINES = (
    {},
    {"ATEN_CPU_CAPABILITY": "default", "MKL_CBWR": "COMPATIBLE", "ONEDNN_MAX_CPU_ISA": "SSE41"},
)


def _stage_env(stage: str) -> str:
    """The ``env ...`` part of ``stage``'s command in dvc.yaml (what it pins)."""
    cmd = _stage_cmd(stage)
    prefix, found, _ = cmd.partition(" python -m generalist_control.")
    assert found and prefix.startswith("env "), cmd
    return prefix


def _train_weights(runs: list[tuple[str, dict]], data_dir: Path, out: Path) -> list[dict]:
    """The policy's weights of tiny trainings run as ``prefix python -m ...train`` per machine.

    ``runs`` holds (command prefix, machine's environment) pairs, all started at once.
    """
    import torch

    procs = []
    for i, (prefix, machine) in enumerate(runs):
        work = out / str(i)
        work.mkdir(parents=True)
        env = {**os.environ, "PYTHONPATH": str(ROOT / "src"), "GC_CONF_DIR": str(ROOT / "conf"),
               **machine}  # fmt: skip
        uri = f"sqlite:///{work / 'mlflow.db'}"  # a few batches, no closed-loop scoring
        args = tiny_train_overrides(data_dir, work, uri, "debug=fast", "closed_loop_val=null",
                                    "monitor=val/loss")  # fmt: skip
        cmd = f"{prefix} {sys.executable} -m generalist_control.train {shlex.join(args)}"
        with (work / "log.txt").open("w") as log:  # the child keeps its own descriptor
            proc = subprocess.Popen(["bash", "-c", cmd], cwd=work, env=env, stdout=log,
                                    stderr=subprocess.STDOUT)  # fmt: skip
        procs.append((work, proc))
    weights = []
    for work, proc in procs:
        assert proc.wait(timeout=300) == 0, (work / "log.txt").read_text()[-3000:]
        ckpt = torch.load(work / "run/models/policy.ckpt", map_location="cpu", weights_only=False)
        weights.append(ckpt["state_dict"])
    return weights


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(a[k].equal(b[k]) for k in a)


@pytest.mark.slow  # four tiny trainings in their own processes at once, ~60 s
def test_train_stage_weights_do_not_depend_on_the_cpu(tiny_data_dir, tmp_path):
    train_pin = _stage_env("train")
    assert _stage_env("evaluate") == train_pin, "evaluate must pin what train pins"
    assert train_pin.startswith(_stage_env("generate")), "train must pin the data stage's numerics"
    runs = [(prefix, m) for prefix in ("env", train_pin) for m in TORCH_MACHINES]
    plain_a, plain_b, pinned_a, pinned_b = _train_weights(runs, tiny_data_dir, tmp_path)
    # unpinned, the emulated machines train different weights: the emulation reproduces it
    assert not _same(plain_a, plain_b)
    assert _same(pinned_a, pinned_b)  # the stage's command: the same weights on both


def test_plots_show_draws_the_declared_plots(repo):
    work, env = repo
    plots = yaml.safe_load((ROOT / "dvc.yaml").read_text())["plots"]
    (work / "dvc.yaml").write_text(yaml.safe_dump({"plots": plots}))
    (work / "reports/eval/plots").mkdir(parents=True)
    rows = ["system,controller,t,r,y,u"]
    rows += [f"cstr,{c},{0.05 * k:.2f},1.0,{1 - 0.9**k:.4f},0.1" for c in ("GC", "LQI")
             for k in range(5)]  # fmt: skip
    (work / "reports/eval/responses.csv").write_text("\n".join(rows) + "\n")
    (work / "reports/eval/plots/cstr_step.png").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(64))
    sh([*DVC, "plots", "show"], work, env)
    html = (work / "dvc_plots/index.html").read_text()
    assert "cstr_step.png" in html, "the PNG figure is not drawn"
    assert "Unit-step responses" in html and '"LQI"' in html, "responses.csv is not drawn"
    ignored = subprocess.run(["git", "check-ignore", "-q", "dvc_plots/index.html"], cwd=ROOT)
    assert ignored.returncode == 0, "dvc_plots/ is not git-ignored"


def test_the_data_writer_is_the_pinned_pyarrow(tmp_path):
    """The parquet footer names its writer: another pyarrow writes other bytes (dvc.lock)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    pins = re.findall(r'^\s*"pyarrow==([^"]+)"', (ROOT / "pyproject.toml").read_text(), re.M)
    assert pins == [pa.__version__], (
        f"pyarrow {pa.__version__} is installed, pyproject.toml pins {pins}: the data's bytes "
        "would not match dvc.lock; rerun the set-up (make setup)"
    )
    pq.write_table(pa.table({"x": [1.0]}), tmp_path / "t.parquet")
    assert pq.ParquetFile(tmp_path / "t.parquet").metadata.created_by.endswith(pins[0])
