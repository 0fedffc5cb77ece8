"""Adding a plant never costs a user file or a half-written result (issue 51, defects 4-10).

The run folder is the command's own only when it is new, empty or an adaptation's (its
marker); two adaptations into one folder do not both write; a diverged adaptation, a bad
plant file, an interrupted publish leave nothing behind. The policies are untrained (their
loops on these stable plants stay bounded); the best-row choice is checked with scripted
closed-loop scores.
"""

from __future__ import annotations

import dataclasses
import os
import signal
import subprocess
import sys
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
import yaml

from generalist_control.adaptation import AdaptationDiverged, adapt, run_folder
from generalist_control.adaptation.job import learn, prepare
from generalist_control.adaptation.new_plant import RecordingError, load_new_plant, write_recorded
from generalist_control.common.atomic import (
    FolderBusy,
    ForeignDirectoryError,
    folder_lock,
    publish_directory,
    staging_directory,
)
from generalist_control.data.generation import generate_demos
from generalist_control.model.bank import ROWS, start_rows
from generalist_control.model.policy import load_policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import PlantConfigError
from helpers import TINY_ADAPT, TINY_DATA, adapt_request, run_command, untrained_policy

REPO = Path(__file__).resolve().parents[1]
#: An adaptation reduced to one fit of one epoch.
QUICK = ("adapt.rounds=0", "adapt.epochs=1")


@pytest.fixture(scope="module")
def base(tmp_path_factory, tiny_demos) -> Path:
    return untrained_policy(tmp_path_factory.mktemp("base"), tiny_demos)


def _plant_file(folder: Path, name: str, **changes) -> Path:
    spec = yaml.safe_load((REPO / "conf/plants/mass_spring_damper.yaml").read_text())
    spec.update({"tag": 77, **changes})
    path = folder / f"{name}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _untouched(tmp_path: Path, run_dir: Path, uri_file: str = "refused.db") -> None:
    """No MLflow store was made, no lock or staging folder is left beside ``run_dir``."""
    assert not (tmp_path / uri_file).exists()
    assert not [p.name for p in run_dir.parent.glob(f".{run_dir.name}.*")]


# --- the run folder: the command's own, never a user's or another command's ----------------


def test_user_files_in_run_dir_are_never_overwritten(base, tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "plants").mkdir(parents=True)
    (run_dir / "adapt.json").write_text('{"mine": true}')
    (run_dir / "plants" / "mass_spring_damper.yaml").write_text("my notes\n")
    uri = f"sqlite:///{tmp_path / 'refused.db'}"
    with pytest.raises(ForeignDirectoryError, match=r"run_dir .*adapt\.json.*Nothing was changed"):
        adapt(adapt_request(base, run_dir, uri))
    assert (run_dir / "adapt.json").read_text() == '{"mine": true}'
    assert (run_dir / "plants" / "mass_spring_damper.yaml").read_text() == "my notes\n"
    _untouched(tmp_path, run_dir)


def test_a_models_folder_is_never_a_run_folder(base, tmp_path):
    """``run_dir=models``: the pipeline's policy (a policy of ours) and metrics stay."""
    models = tmp_path / "models"
    models.mkdir()
    policy = models / "policy.ckpt"
    policy.write_bytes(base.read_bytes())
    (models / "metrics.json").write_text('{"val/loss": 0.1}')
    uri = f"sqlite:///{tmp_path / 'refused.db'}"
    with pytest.raises(ForeignDirectoryError, match=r"metrics\.json, policy\.ckpt"):
        adapt(adapt_request(base, models, uri))
    assert policy.read_bytes() == base.read_bytes()
    assert sorted(p.name for p in models.iterdir()) == ["metrics.json", "policy.ckpt"]
    _untouched(tmp_path, models)


def test_another_commands_output_folder_is_never_a_run_folder(base, tmp_path):
    demos = tmp_path / "demos"
    with staging_directory(demos) as staging:
        (staging / "demos.parquet").write_bytes(b"data")
        publish_directory(staging, demos, {}, "paths.data_dir")
    with pytest.raises(ForeignDirectoryError, match=r"another command \(paths\.data_dir"):
        adapt(adapt_request(base, demos, f"sqlite:///{tmp_path / 'refused.db'}"))
    assert (demos / "demos.parquet").read_bytes() == b"data"


def test_an_adaptations_folder_is_replaced_and_a_file_added_to_it_stops_the_next(
    base, tmp_path, mlflow_uri
):
    run_dir = tmp_path / "run"
    for plant in ("mass_spring_damper", "dc_motor_speed"):
        _, objects = adapt(adapt_request(base, run_dir, mlflow_uri, plant, *QUICK))
    _, meta = load_policy(objects["policy_path"])
    assert "dc_motor_speed" in meta["tags"] and "mass_spring_damper" not in meta["tags"]
    assert sorted(p.name for p in (run_dir / "plants").iterdir()) == ["dc_motor_speed.yaml"]
    (run_dir / "notes.txt").write_text("mine")
    before = (run_dir / "policy.ckpt").read_bytes()
    with pytest.raises(ForeignDirectoryError, match="notes.txt"):
        adapt(adapt_request(base, run_dir, mlflow_uri, "mass_spring_damper", *QUICK))
    assert (run_dir / "policy.ckpt").read_bytes() == before


def test_a_second_adaptation_into_a_run_dir_being_written_is_refused(base, tmp_path):
    run_dir = tmp_path / "run"
    uri = f"sqlite:///{tmp_path / 'refused.db'}"
    with folder_lock(run_dir, "adaptation", wait=False):
        with pytest.raises(FolderBusy, match=rf"{run_dir} is being written by adaptation pid"):
            adapt(adapt_request(base, run_dir, uri))
    assert not run_dir.exists()
    _untouched(tmp_path, run_dir)


def test_an_interrupted_publish_leaves_no_run_folder_and_ends_the_run_killed(
    base, tmp_path, mlflow_uri, monkeypatch
):
    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_folder, "publish_directory", interrupted)
    run_dir = tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        adapt(adapt_request(base, run_dir, mlflow_uri, "mass_spring_damper", *QUICK))
    assert not run_dir.exists()
    _untouched(tmp_path, run_dir)
    mlflow.set_tracking_uri(mlflow_uri)
    runs = mlflow.search_runs(experiment_names=["generalist-control/adapt"],
                              filter_string=f"tags.run_dir = '{run_dir}'")  # fmt: skip
    assert list(runs["status"]) == ["KILLED"]


def _command(base: Path, tmp_path: Path, uri: str, plant: str) -> list[str]:
    overrides = [f"plant={plant}", f"policy={base}", f"run_dir={tmp_path / 'run'}",
                 f"logger.tracking_uri={uri}",
                 f"logger.artifact_location={tmp_path / 'mlruns'}",
                 "adapt.rounds=0", *TINY_ADAPT]  # fmt: skip
    return [sys.executable, "adapt.py", *overrides]


@pytest.mark.slow
def test_sigterm_during_publish_exits_non_zero_and_publishes_nothing(base, tmp_path, mlflow_uri):
    """A real SIGTERM while the folder is swapped in (held there): exit 143, the run KILLED."""
    hold = (
        "import sys, time; from generalist_control.adaptation import run_folder; "
        "run_folder.publish_directory = lambda *a, **k: (print('publishing', flush=True), "
        "time.sleep(120)); sys.argv = sys.argv[1:]; "
        "from generalist_control.adapt import main; main()"
    )
    cmd = _command(base, tmp_path, mlflow_uri, "mass_spring_damper")
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.Popen([sys.executable, "-c", hold, *cmd[1:]], cwd=REPO, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        for line in proc.stdout:  # type: ignore[union-attr]
            if line.strip() == "publishing":
                proc.send_signal(signal.SIGTERM)
                break
        assert proc.wait(timeout=60) == 128 + signal.SIGTERM, proc.stderr.read()[-2000:]
    finally:
        proc.kill()
    assert not (tmp_path / "run").exists()
    _untouched(tmp_path, tmp_path / "run")
    mlflow.set_tracking_uri(mlflow_uri)
    runs = mlflow.search_runs(experiment_names=["generalist-control/adapt"],
                              filter_string=f"tags.run_dir = '{tmp_path / 'run'}'")  # fmt: skip
    assert list(runs["status"]) == ["KILLED"]


@pytest.mark.slow
def test_a_refused_command_exits_non_zero_and_leaves_no_folder(base, tmp_path):
    """A user plant file named like a catalogue plant, refused by ``python adapt.py``."""
    cstr = _plant_file(tmp_path, "cstr")
    cmd = [sys.executable, "-m", "generalist_control.adapt", f"plant={cstr}", f"policy={base}",
           f"logger.tracking_uri=sqlite:///{tmp_path / 'refused.db'}", *TINY_ADAPT]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO / "src")}
    proc = run_command(cmd, cwd=tmp_path, env=env, timeout=300)
    assert proc.returncode == 1
    assert f"{cstr}: the file's stem 'cstr' is the name of a catalogue plant" in proc.stderr
    assert [p.name for p in tmp_path.iterdir()] == ["cstr.yaml"]  # no outputs/adapt/<time>


# --- a diverged adaptation is refused; the best row is kept, never one worse than the start --


def _recording(tmp_path: Path, u_factor: float = 1.0) -> Path:
    plant = load_plant("mass_spring_damper")
    demos = generate_demos([plant], TINY_DATA, progress=False)
    return write_recorded(tmp_path / "rec.csv", plant, demos.x, demos.r, demos.y,
                          demos.u * u_factor)  # fmt: skip


@pytest.mark.parametrize("case", ["unstable_plant", "recording_u_1e30"])
def test_a_diverged_adaptation_is_refused_and_nothing_registered(base, tmp_path, case):
    if case == "unstable_plant":  # poles +-20: the A = [[0, 1], [400, 0]]
        plant, extra = str(_plant_file(tmp_path, "upright", A=[[0.0, 1.0], [400.0, 0.0]])), ()
    else:
        plant, extra = "mass_spring_damper", (f"demos={_recording(tmp_path, 1e30)}",)
    run_dir = tmp_path / "run"
    uri = f"sqlite:///{tmp_path / 'refused.db'}"
    with pytest.raises(AdaptationDiverged, match="closed loop diverges.*nothing was written"):
        adapt(adapt_request(base, run_dir, uri, plant, *extra))
    assert not run_dir.exists()
    _untouched(tmp_path, run_dir)


class _Scripted:
    """Closed-loop scores in a given order; each call keeps the row it scored."""

    def __init__(self, tag: int, scores: list[float]) -> None:
        self.tag, self.scores, self.rows = tag, list(scores), []

    def __call__(self, policy, meta) -> float:
        self.rows.append(policy.state_dict()[ROWS][self.tag].clone())
        return self.scores.pop(0)


@pytest.fixture(scope="module")
def three_rounds(base, tmp_path_factory, mlflow_uri):
    """A job with three short DAgger rounds (one rollout per round, 2 s)."""
    run_dir = tmp_path_factory.mktemp("rounds") / "run"
    short = ("adapt.rounds=3", "adapt.epochs=1", "dagger.sampler.rollouts=1",
             "dagger.sampler.duration=2.0", "dagger.sampler.families=0")  # fmt: skip
    return prepare(adapt_request(base, run_dir, mlflow_uri, "mass_spring_damper", *short))


@pytest.mark.parametrize(
    ("scores", "kept"),
    [
        ([0.5, 0.6, 0.3, 0.9, 0.4], 2),
        ([0.2, 0.5, 0.6, 0.7, 0.6], 0),
        ([0.5, 0.4, 0.4, 0.9, 0.8], 2),
    ],
    ids=["best-round", "start-beats-every-fit", "later-on-a-tie"],
)
def test_the_row_kept_is_the_best_scored_never_worse_than_the_start(three_rounds, scores, kept):
    """Scores of the start, the fit and three DAgger rounds, in that order."""
    tag = three_rounds.new.plant.tag
    script = _Scripted(tag, scores)
    policy, _, record = learn(dataclasses.replace(three_rounds, score=script))
    assert len(script.rows) == 5 and not torch.equal(script.rows[1], script.rows[0])
    assert torch.equal(policy.state_dict()[ROWS][tag], script.rows[kept])
    loop = record["closed_loop"]
    assert loop["kept"] == scores[kept] and loop["rounds"] == scores[2:]
    assert loop["kept_from"] == ["start", "fit", "round 1", "round 2", "round 3"][kept]


def test_the_mean_start_row_averages_the_trained_rows_only(base):
    policy, meta = load_policy(base)
    rows = policy.state_dict()[ROWS].double()
    trained = sorted(meta["tags"].values())  # cstr 10, hydraulic_actuator 13 of 25 rows
    mean = start_rows(policy, meta["tags"].values())["mean"].double()
    np.testing.assert_allclose(mean.numpy(), rows[trained].mean(0).numpy(), rtol=1e-6)
    assert not np.allclose(mean.numpy(), rows.mean(0).numpy(), rtol=1e-3)


def test_recorded_demonstrations_keep_the_previous_control_channel(tiny_demos, tmp_path):
    """A policy that reads the previous control: a recording gives the data stage's windows."""
    pol = untrained_policy(tmp_path, tiny_demos, channels=["integral", "previous_control"])
    rec = _recording(tmp_path)
    job = prepare(adapt_request(pol, tmp_path / "run", "sqlite:///unused.db",
                                "mass_spring_damper", f"demos={rec}"))  # fmt: skip
    plant = load_plant("mass_spring_damper")
    demos = generate_demos([plant], TINY_DATA, progress=False)
    want = demos.windows(8, 3, True, True)
    assert want.state.shape[-1] == demos.windows(8, 3, True, False).state.shape[-1] + 1
    for key in ("state", "mask", "ref", "target"):
        np.testing.assert_array_equal(getattr(job.windows, key), getattr(want, key), key)


# --- the plant file: checked once, the file named in every refusal -------------------------

META = {"tags": {"cstr": 10, "hydraulic_actuator": 13}, "dt": 0.05}


@pytest.mark.parametrize(
    ("name", "changes", "match"),
    [
        ("my_plant", {"tag": -3}, "field 'tag' must be a non-negative integer.*got -3"),
        ("my_plant", {"tag": "abc"}, "field 'tag' must be a non-negative integer.*got 'abc'"),
        ("my.plant", {}, r"letters, digits and underscores.*rename the file, e\.g\. my_plant"),
        ("cstr", {}, "stem 'cstr' is the name of a catalogue plant.*rename the file"),
        ("huge", {"A": [[0.0, 1.0], [-1e300, -1.0]]}, "'A' has an entry of 1e\\+300.*rescale"),
        ("used_tag", {"tag": 13}, "its tag 13 is a tag this policy uses.*e.g. 14"),
    ],
    ids=["negative-tag", "text-tag", "dotted-name", "catalogue-name", "huge-entry", "used-tag"],
)
def test_a_plant_file_is_refused_naming_the_file(tmp_path, name, changes, match):
    path = _plant_file(tmp_path, name, **changes)
    with pytest.raises(PlantConfigError, match=match) as info:
        load_new_plant(str(path), META)
    assert str(info.value).startswith(f"{path}: ")


def test_a_plant_file_that_is_a_list_or_not_yaml_is_refused_naming_it(tmp_path):
    listed = tmp_path / "listed.yaml"
    listed.write_text("- tag: 30\n- dt: 0.05\n")
    with pytest.raises(PlantConfigError, match=f"{listed}: .*holds a list, not the mapping"):
        load_new_plant(str(listed), META)
    broken = tmp_path / "broken.yaml"
    broken.write_text("tag: [30\n")
    with pytest.raises(PlantConfigError, match=f"{broken}: not a YAML file"):
        load_new_plant(str(broken), META)


def test_a_corrupt_recording_is_refused_naming_the_file(base, tmp_path):
    bad = tmp_path / "rec.parquet"
    bad.write_bytes(b"PAR1 not really a parquet file")
    with pytest.raises(RecordingError, match=f"{bad}: not a readable parquet file.*again"):
        prepare(adapt_request(base, tmp_path / "run", "sqlite:///unused.db",
                              "mass_spring_damper", f"demos={bad}"))  # fmt: skip
