"""The ablation pipeline (``ablation/dvc.yaml``): its stages, their commands, its parallel runner.

Nothing trains here (``tests/test_pipeline.py`` runs the pipeline on tiny data): DVC reads
the pipeline in a throw-away repository, every stage command is composed with Hydra's
compose API (the overrides it gives, as the entry point would see them) and checked against
the issue's points, and ``scripts/ablation.sh`` runs a pipeline of the same layout whose
stages sleep, two at a time.
"""

from __future__ import annotations

import os
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir

ROOT = Path(__file__).resolve().parents[1]
DVC = [sys.executable, "-m", "dvc"]
#: The issue's points: d at M = 3, M at d = 32, a second seed (43) of d16, d32 and m1.
POINTS = {
    "d16": (16, 3, 42), "d32": (32, 3, 42), "d64": (64, 3, 42), "m1": (32, 1, 42),
    "m5": (32, 5, 42), "d16_seed43": (16, 3, 43), "d32_seed43": (32, 3, 43),
    "m1_seed43": (32, 1, 43),
}  # fmt: skip
RECIPES = ("default", "paper")


def _env() -> dict[str, str]:
    path = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    env = {**os.environ, "DVC_NO_ANALYTICS": "1", "GIT_AUTHOR_NAME": "t",
           "GIT_AUTHOR_EMAIL": "t@t", "GIT_COMMITTER_NAME": "t", "GIT_COMMITTER_EMAIL": "t@t",
           "PATH": path}  # fmt: skip
    env.pop("MLFLOW_TRACKING_URI", None)
    return env


def _sh(cmd: list[str], cwd: Path, **env: str) -> str:
    proc = subprocess.run(
        cmd, cwd=cwd, env={**_env(), **env}, capture_output=True, text=True, timeout=300
    )
    assert proc.returncode == 0, f"{cmd}:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"
    return proc.stdout + proc.stderr


def _repo(tmp_path: Path, pipeline: str | None = None) -> Path:
    """A git + DVC repository with the project's pipelines and runner (or ``pipeline``)."""
    work = tmp_path / "repo"
    (work / "ablation").mkdir(parents=True)
    (work / "scripts").mkdir()
    shutil.copy(ROOT / "scripts" / "ablation.sh", work / "scripts")
    shutil.copy(ROOT / "dvc.yaml", work)
    shutil.copy(ROOT / "ablation" / ".gitignore", work / "ablation")
    if pipeline is None:
        shutil.copy(ROOT / "ablation" / "dvc.yaml", work / "ablation")
    else:
        (work / "ablation" / "dvc.yaml").write_text(pipeline)
    _sh(["git", "init", "-q"], work)
    _sh([*DVC, "init", "-q"], work)
    return work


def _stages(work: Path) -> dict:
    from dvc.repo import Repo

    with Repo(str(work)) as repo:
        return {s.name: s for s in repo.index.stages if s.path_in_repo == "ablation/dvc.yaml"}


def _compose(cmd: str) -> tuple[str, object]:
    """The entry point of ``python -m generalist_control.<stage> <overrides>`` and its config."""
    words = shlex.split(cmd)
    assert words[:2] == ["python", "-m"] and words[2].startswith("generalist_control."), cmd
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return words[2].split(".")[-1], compose("config", words[3:], return_hydra_config=True)


#: The overrides of a point's commands that hold the point: its values, its key in paths.
POINT_KEYS = ("model.hidden", "experts", "seed", "paths.models_dir", "run_dir", "policy",
              "logger.run_name", "paths.reports_dir")  # fmt: skip


def _compose_point(cmd: str, key: str, composed: dict) -> tuple[str, object]:
    """``_compose(cmd)``, composed once per entry point and recipe: a later point's command
    must be the first's with only its own values (:data:`POINT_KEYS`) changed."""
    words = shlex.split(cmd)
    stage, overrides = words[2], dict(w.split("=", 1) for w in words[3:])
    if stage not in composed:
        composed[stage] = (overrides, *_compose(cmd))
        return composed[stage][1:]
    first, name, cfg = composed[stage]
    assert overrides.keys() == first.keys(), cmd
    assert {k: v for k, v in overrides.items() if k not in POINT_KEYS} == {
        k: v for k, v in first.items() if k not in POINT_KEYS
    }, cmd
    cfg = cfg.copy()
    for k in POINT_KEYS:
        if k not in overrides:
            continue
        value: object = overrides[k]
        if k in ("model.hidden", "experts", "seed"):
            value = int(overrides[k])
        else:  # the point's own folder or run name
            assert key in re.split(r"[/-]", overrides[k]), (k, overrides[k])
        OmegaConf.update(cfg, k, value, merge=False)
    return name, cfg


def _outs(stage) -> dict[str, bool]:
    """Each output's path and whether DVC caches it."""
    return {str(o.def_path): bool(o.use_cache) for o in stage.outs}


def test_the_stages_are_the_issues_points_and_their_commands_compose(tmp_path):
    stages = _stages(_repo(tmp_path))
    expected = {f"{r}@{p}" for r in RECIPES for p in POINTS} | {f"report@{r}" for r in RECIPES}
    assert set(stages) == expected
    groups, eval_dirs = {}, {}
    for recipe in RECIPES:
        composed = {}  # a point's commands differ from the first's only in the point's values
        for key, (d, m, seed) in POINTS.items():
            stage = stages[f"{recipe}@{key}"]
            (train, cfg), (evaluate, ecfg) = (_compose_point(c, key, composed) for c in stage.cmd)
            assert (train, evaluate) == ("train", "evaluate")
            assert (cfg.model.hidden, cfg.experts, cfg.seed) == (d, m, seed)
            # the recipe: the paper's data, network and training, or the default's
            paper = recipe == "paper"
            assert cfg.paths.data_dir == ("data/paper" if paper else "data/demos")
            assert cfg.model.window_scale is not paper and (cfg.dagger is None) is paper
            assert cfg.paths.data_dir in {str(x.def_path) for x in stage.deps}
            # the evaluation evaluates what the training wrote, and DVC keeps both
            assert ecfg.policy == f"{cfg.paths.models_dir}/policy.ckpt"
            assert ecfg.evaluation.plots is False
            outs = _outs(stage)
            assert outs[ecfg.policy] is True
            assert outs[f"{cfg.paths.models_dir}/metrics.json"] is False  # git
            assert outs[f"{ecfg.paths.reports_dir}/summary.json"] is False  # git
            assert outs[f"{ecfg.paths.reports_dir}/metrics.csv"] is True
            assert cfg.logger.experiment_name == ecfg.logger.experiment_name
            groups.setdefault(recipe, set()).add(cfg.hydra.callbacks.mlflow_sweep.group)
            eval_dirs.setdefault(recipe, set()).add(str(Path(ecfg.paths.reports_dir).parent))
        # the report reads the recipe's group and evaluations, and depends on them
        (name, rcfg) = _compose(stages[f"report@{recipe}"].cmd)
        assert name == "report" and groups[recipe] == {f"ablation:{recipe}"}
        assert rcfg.report.parent_run == f"ablation:{recipe}"
        assert eval_dirs[recipe] == {rcfg.report.evaluations_dir}
        deps = {str(x.def_path) for x in stages[f"report@{recipe}"].deps}
        assert rcfg.report.evaluations_dir in deps
        assert rcfg.report.experiment_name == cfg.logger.experiment_name
        outs = _outs(stages[f"report@{recipe}"])
        for name in ("summary.json", "runs.csv", "claims.csv", "comparison.md"):
            assert outs[f"{rcfg.report.out_dir}/{name}"] is False, name


def test_cached_outputs_are_ignored_by_git_and_the_others_are_not(tmp_path):
    """DVC then writes no .gitignore into a folder that a stage replaces as a whole."""
    work = _repo(tmp_path)
    outs = {p: cached for s in _stages(work).values() for p, cached in _outs(s).items()}
    paths = sorted(outs)
    proc = subprocess.run(["git", "check-ignore", "--stdin"], cwd=work, input="\n".join(paths),
                          capture_output=True, text=True)  # fmt: skip
    ignored = set(proc.stdout.split())
    assert {p for p in paths if outs[p]} == ignored


SLEEPY = """
vars:
  - points: {a: {n: 1}, b: {n: 2}, c: {n: 3}}
stages:
  default:
    foreach: ${points}
    do:
      cmd: >-
        python -c "import time; t0 = time.time(); time.sleep(3);
        open('out_${key}', 'w').write(f'{t0} {time.time()}')"
      outs:
        - out_${key}
  report:
    foreach: [default]
    do:
      cmd: cat out_a out_b out_c > report_${item}
      deps: [out_a, out_b, out_c]
      outs:
        - report_${item}
"""


@pytest.mark.slow
def test_the_runner_runs_two_points_at_once_then_the_report(tmp_path):
    work = _repo(tmp_path, SLEEPY)
    env = {"ABLATION_UPSTREAM": "", "DVC": shlex.join(DVC)}
    out = _sh(["bash", "scripts/ablation.sh", "default"], work, **env)
    assert "3 points, 2 at a time" in out
    times = {k: [float(x) for x in (work / "ablation" / f"out_{k}").read_text().split()]
             for k in "abc"}  # fmt: skip
    first, second = sorted(times.values())[:2]
    assert second[0] < first[1], times  # the first two ran side by side
    assert (work / "ablation" / "report_default").is_file()
    lock = (work / "ablation" / "dvc.lock").read_text()
    assert all(f"default@{k}:" in lock for k in "abc")  # each recorded, none lost
    again = _sh(["bash", "scripts/ablation.sh", "default"], work, **env)
    assert "Running stage" not in again  # all up to date: a rerun resumes, runs nothing


def test_the_runner_lists_the_real_pipelines_points(tmp_path):
    work = _repo(tmp_path)
    dry = {"GC_ABLATION_DRY_RUN": "1", "DVC": shlex.join(DVC)}
    out = _sh(["bash", "scripts/ablation.sh"], work, **dry)
    runs = [line for line in out.splitlines() if "--single-item" in line]
    assert len(runs) == 16 and "16 points, 2 at a time" in out
    assert "repro generate" in out  # the default recipe's data, first
    assert "repro ablation/dvc.yaml:report@default" in out
    assert "repro ablation/dvc.yaml:report@paper" in out
    paper = _sh(["bash", "scripts/ablation.sh", "paper"], work, ABLATION_JOBS="3", **dry)
    assert "8 points, 3 at a time" in paper and "report@default" not in paper
