"""Adding a plant to a trained policy: only its row is learned, bad input is refused.

The fast tests adapt a small policy that was not trained (its normaliser fitted on the tiny
data), a few steps each: what is checked is what changes and what is refused, not how well it
controls. ``test_adapted_tiny_policy_closes_the_loop`` (slow) trains a tiny policy first.
"""

from __future__ import annotations

import sys
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch
import yaml

from generalist_control.adaptation import adapt
from generalist_control.adaptation.job import learn, prepare
from generalist_control.adaptation.new_plant import RecordingError, write_recorded
from generalist_control.data.generation import generate_demos
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.bank import ROWS, SCALES, RecipeError, grow_policy, plant_scales
from generalist_control.model.policy import load_policy, policy_sha256
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import PlantConfigError
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import PerPlantController, Run, simulate_many
from generalist_control.tracking.mlflow_utils import find_training_run
from helpers import (
    TINY_ADAPT,
    TINY_DATA,
    adapt_request,
    compose_cfg,
    run_command,
    tiny_train_overrides,
    untrained_policy,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def base(tmp_path_factory, tiny_demos) -> Path:
    return untrained_policy(tmp_path_factory.mktemp("base"), tiny_demos)


def _adapt(policy, run_dir: Path, uri: str, plant: str = "mass_spring_damper", *extra: str):
    record, objects = adapt(adapt_request(policy, run_dir, uri, plant, *extra))
    return record, objects


@pytest.fixture(scope="module")
def adapted(base, tmp_path_factory, mlflow_uri) -> tuple[Path, dict, dict]:
    """``base`` adapted to mass_spring_damper by the default request, once for the tests that
    check what that one adaptation wrote: its run folder, its record and its objects."""
    run_dir = tmp_path_factory.mktemp("adapted") / "run"
    record, objects = _adapt(base, run_dir, mlflow_uri)
    return run_dir, record, objects


def test_only_the_new_row_changes_bit_for_bit(base, adapted):
    old, old_meta = load_policy(base)
    _, record, objects = adapted
    new, meta = load_policy(objects["policy_path"])
    n = old.net.n_tags
    assert new.net.n_tags == n + 1 and new.config["plant"]["n_tags"] == n + 1
    assert meta["tags"] == {**old_meta["tags"], "mass_spring_damper": n}
    before, after = old.state_dict(), new.state_dict()
    assert set(before) == set(after)
    for key, value in before.items():
        if key == ROWS or key in SCALES:  # grown by one row; the old rows bit for bit
            assert torch.equal(after[key][:n], value), key
            assert after[key].shape[0] == n + 1, key
        else:
            assert torch.equal(after[key], value), key
    start = old.state_dict()[ROWS][[old_meta["tags"][k] for k in ("cstr", "hydraulic_actuator")]]
    assert not any(torch.equal(after[ROWS][n], row) for row in (*start, start.mean(0)))
    assert record["learned"] == [f"{ROWS}[{n}]"]
    assert bool(after["normaliser.seen"][n])


def test_grown_scales_are_the_plant_windows_rms(base, tiny_demos):
    """The new normaliser row against a hand computation on the plant's windows."""
    plant = load_plant("mass_spring_damper")
    demos = generate_demos([plant], TINY_DATA, progress=False)
    w = demos.windows(8, 3, True)
    t = {k: torch.from_numpy(getattr(w, k)) for k in ("state", "mask", "ref", "target")}
    old, _ = load_policy(base)
    grown = grow_policy(old, torch.zeros(16), plant_scales(**t))
    x, m = w.state.astype(np.float64), w.mask.astype(np.float64)
    rms = np.sqrt(((x * m) ** 2).sum((0, 1)) / np.maximum(m.sum((0, 1)), 1))
    rms[m.sum((0, 1)) == 0] = 1.0  # padding: scale one
    n = old.net.n_tags
    got = grown.normaliser
    np.testing.assert_allclose(got.state_scale[n].numpy(), rms, rtol=1e-6)
    np.testing.assert_allclose(float(got.ref_scale[n]), np.sqrt(np.mean(w.ref**2.0)), rtol=1e-6)
    u = np.sqrt(np.mean(w.target.astype(np.float64) ** 2))
    np.testing.assert_allclose(float(got.control_scale[n]), u, rtol=1e-6)
    assert torch.equal(grown.state_dict()[ROWS][n], torch.zeros(16))


def test_unfreeze_moves_the_named_parameters_and_no_others(base, tmp_path, mlflow_uri):
    """The learning alone (this untrained policy's loop diverges once its skip gains move)."""
    old, _ = load_policy(base)
    request = adapt_request(base, tmp_path / "run", mlflow_uri, "mass_spring_damper",
                       "adapt.unfreeze=[net.skip.gains]", "adapt.rounds=0")  # fmt: skip
    new, _, _ = learn(prepare(request))
    before, after = old.state_dict(), new.state_dict()
    moved = {
        k for k in before if k != ROWS and k not in SCALES and not torch.equal(before[k], after[k])
    }
    assert moved == {"net.skip.gains.weight", "net.skip.gains.bias"}
    assert torch.equal(after[ROWS][: old.net.n_tags], before[ROWS])


def test_runtime_resets_on_the_new_plant_and_adapting_twice_grows_again(
    adapted, tmp_path, mlflow_uri
):
    _, _, first = adapted  # base adapted to mass_spring_damper
    _, second = _adapt(first["policy_path"], tmp_path / "two", mlflow_uri, "dc_motor_speed")
    one, _ = load_policy(first["policy_path"])
    two, meta = load_policy(second["policy_path"])
    n = one.net.n_tags
    assert two.net.n_tags == n + 1
    assert meta["tags"]["mass_spring_damper"] == n - 1 and meta["tags"]["dc_motor_speed"] == n
    assert torch.equal(two.state_dict()[ROWS][:n], one.state_dict()[ROWS])
    assert set(meta["adapted"]) == {"mass_spring_damper", "dc_motor_speed"}
    rt = PolicyRuntime.load(second["policy_path"])
    for name in ("mass_spring_damper", "dc_motor_speed", "cstr"):
        rt.reset(name)
        plant = load_plant(name)
        u = [rt.step(np.zeros(plant.order), 1.0) for _ in range(3)]
        assert np.all(np.isfinite(u)), name


def test_the_run_is_its_own_in_the_adapt_experiment(adapted, mlflow_uri):
    run_dir, record, objects = adapted
    assert objects["experiment"] == "generalist-control/adapt"
    mlflow.set_tracking_uri(mlflow_uri)
    run = mlflow.get_run(objects["run_id"])
    assert run.info.status == "FINISHED"
    assert run.data.params["plant"] == "mass_spring_damper"
    assert run.data.tags["adapt.plant"] == "mass_spring_damper"
    assert {"adapt/closed_loop", "adapt/wall_s", "adapt/loss"} <= set(run.data.metrics)
    _, meta = load_policy(objects["policy_path"])
    assert "mlflow_run_id" not in meta  # the file's bytes reproduce; its run is found by hash
    assert find_training_run(policy_sha256(objects["policy_path"])) == objects["run_id"]
    assert (run_dir / "adapt.json").is_file()
    assert (run_dir / "plants" / "mass_spring_damper.yaml").is_file()
    demos = record["demonstrations"]
    assert demos["source"] == "generated" and demos["windows"] == 8 * 38  # 8 steps, 40 samples
    assert demos["dagger_windows"] > 0


def test_recorded_demonstrations_train_the_row_without_dagger(base, tmp_path, mlflow_uri):
    """The recorded controller is the baseline: its controls, open loop; LQI in closed loop."""
    path = _recording(tmp_path)
    record, objects = _adapt(base, tmp_path / "run", mlflow_uri, "mass_spring_damper",
                             f"demos={path}")  # fmt: skip
    demos = record["demonstrations"]
    assert demos == {"source": str(path), "expert": "recorded", "trajectories": 8,
                     "windows": 8 * 38, "dagger_windows": 0}  # fmt: skip
    assert record["closed_loop"]["rounds"] == []
    assert np.isfinite(record["recorded_relative_mse"])
    _, meta = load_policy(objects["policy_path"])
    assert meta["adapted"]["mass_spring_damper"]["demonstrations"]["expert"] == "recorded"


# --- refusals: a clear message, and nothing written (no run folder, no MLflow store) ---


def _plant_file(tmp: Path, name: str, **changes) -> Path:
    spec = yaml.safe_load((REPO / "conf/plants/mass_spring_damper.yaml").read_text())
    spec.update({"tag": 77, **changes})
    path = tmp / f"{name}.yaml"
    path.write_text(yaml.safe_dump(spec))
    return path


def _refused(policy, tmp_path: Path, plant: str, match: str, *extra: str, error=ValueError):
    uri = f"sqlite:///{tmp_path / 'refused.db'}"
    with pytest.raises(error, match=match):
        _adapt(policy, tmp_path / "run", uri, plant, *extra)
    assert not (tmp_path / "run").exists()
    assert not (tmp_path / "refused.db").exists()


def test_refuses_a_plant_unfit_for_lqi(base, tmp_path):
    # the double integrator's velocity as output: a zero at s = 0
    path = _plant_file(tmp_path, "velocity_only", A=[[0.0, 1.0], [0.0, 0.0]], B=[[0.0], [1.0]],
                       C=[[0.0, 1.0]])  # fmt: skip
    _refused(base, tmp_path, str(path), "unfit for LQI.*transmission zero at s = 0",
             error=PlantConfigError)  # fmt: skip


def test_refuses_an_order_above_max_order(base, tmp_path):
    states = [{"name": f"s{i}", "unit": "-"} for i in range(5)]
    path = _plant_file(tmp_path, "fifth_order", states=states, A=np.eye(5).tolist(),
                       B=[[1.0]] * 5, C=[[1.0] * 5], lqi={"Q": [1.0] * 6, "R": 1.0})  # fmt: skip
    _refused(base, tmp_path, str(path), "5 states.*orders 1..4 are supported",
             error=PlantConfigError)  # fmt: skip


def test_refuses_a_name_the_policy_already_has(base, tmp_path):
    _refused(base, tmp_path, "cstr", "already a plant of this policy.*its own name",
             error=PlantConfigError)  # fmt: skip


def test_refuses_a_file_tag_the_policy_uses_and_another_dt(base, tmp_path):
    used = _plant_file(tmp_path, "my_plant", tag=10)
    _refused(base, tmp_path, str(used), "tag 10 is a tag this policy uses.*e.g. 14",
             error=PlantConfigError)  # fmt: skip
    slow = _plant_file(tmp_path, "slow_plant", dt=0.1)
    _refused(base, tmp_path, str(slow), "dt = 0.1 s, the policy runs at dt = 0.05 s",
             error=PlantConfigError)  # fmt: skip


def _recording(tmp_path: Path, edit=None) -> Path:
    """An LQI simulation of mass_spring_damper as a recorded CSV, ``edit`` applied to it."""
    plant = load_plant("mass_spring_damper")
    demos = generate_demos([plant], TINY_DATA, progress=False)
    path = write_recorded(tmp_path / "rec.csv", plant, demos.x, demos.r, demos.y, demos.u)
    if edit is not None:
        edit(pd.read_csv(path)).to_csv(path, index=False)
    return path


@pytest.mark.parametrize(
    ("edit", "match"),
    [
        (
            lambda df: df.assign(y=df.y.where(df.index != 17)),
            "column 'y' is NaN or infinite at row 17",
        ),
        (lambda df: df.drop(columns=["u"]), r"lacks the columns \['u'\]"),
        (lambda df: df.assign(t=df.t * 2), "0.1 s apart.*dt = 0.05 s"),
        (lambda df: df.assign(x2=0.0), r"state columns \['x2'\] beyond"),
    ],
    ids=["nan", "missing-column", "other-dt", "extra-state"],
)
def test_refuses_bad_recorded_demonstrations(base, tmp_path, edit, match):
    path = _recording(tmp_path, edit)
    _refused(base, tmp_path, "mass_spring_damper", match, f"demos={path}", error=RecordingError)


def test_refuses_a_tag_free_row(tiny_demos, tmp_path):
    free = untrained_policy(tmp_path, tiny_demos, "free.ckpt", plant="inferred", models=None)
    _refused(free, tmp_path, "mass_spring_damper", "tag-free.*no row to learn.*Evaluate it "
             "directly: adapt.learn=false", error=RecipeError)  # fmt: skip


def test_refuses_unfreezing_the_rows_or_an_unknown_name(base, tmp_path):
    _refused(base, tmp_path, "mass_spring_damper", "holds the trained plants' rows",
             "adapt.unfreeze=[net.plant]")  # fmt: skip
    _refused(base, tmp_path, "mass_spring_damper", "no parameter of the policy.*net.skip",
             "adapt.unfreeze=[net.nowhere]")  # fmt: skip


# --- the tag-free policy named for a plant, and an evaluation of a plant outside conf/ ---


def test_tag_free_named_only_changes_one_normaliser_row(tiny_demos, tmp_path, mlflow_uri):
    free = untrained_policy(tmp_path, tiny_demos, "free.ckpt", plant="inferred", models=None)
    old, _ = load_policy(free)
    _, objects = _adapt(free, tmp_path / "run", mlflow_uri, "mass_spring_damper",
                        "adapt.learn=false")  # fmt: skip
    new, meta = load_policy(objects["policy_path"])
    tag = meta["tags"]["mass_spring_damper"]
    assert new.net.n_tags == old.net.n_tags and tag == 0  # its file's tag, a free row
    before, after = old.state_dict(), new.state_dict()
    for key, value in before.items():
        rows = [t for t in range(value.shape[0]) if t != tag] if key in SCALES else slice(None)
        assert torch.equal(after[key][rows], value[rows]), key
    assert bool(after["normaliser.seen"][tag]) and not bool(before["normaliser.seen"][tag])


def test_evaluate_finds_a_plant_file_outside_the_catalogue(base, tmp_path, mlflow_uri):
    from generalist_control.evaluate import run as evaluate_run

    path = _plant_file(tmp_path, "my_spring", tag=30)
    run_dir = tmp_path / "run"
    _, objects = _adapt(base, run_dir, mlflow_uri, str(path), "adapt.epochs=1", "adapt.rounds=0")
    cfg = compose_cfg(
        f"hydra.searchpath=[file://{run_dir.resolve()}]",
        "+plants@systems.plants.my_spring=my_spring", "systems.include=[my_spring]",
        f"policy={objects['policy_path']}",
        f"paths.reports_dir={tmp_path / 'eval'}", f"logger.tracking_uri={mlflow_uri}",
        "~evaluation.scenarios", "+evaluation.scenarios={step:{kind:step,duration:3.0}}",
        "evaluation.plots=false", "evaluation.setpoint=null", "evaluation.backend=torch",
    )  # fmt: skip
    summary = evaluate_run(cfg)
    assert summary["ratios"]["step"]["worst_ISE_system"] == "my_spring"
    assert (tmp_path / "eval" / "metrics.csv").is_file()


# --- slow: a trained tiny policy, adapted, in closed loop against LQI; the command line ---


def _unit_step_errors(policy_path, plant_name: str) -> tuple[float, bool]:
    """GC's output error against LQI's on a unit step, relative to LQI's (simulated here)."""
    plant = load_plant(plant_name)
    r = np.ones((1, 200)) * plant.amplitude_scale
    rt = PolicyRuntime.load(policy_path, backend="torch")
    (gc,) = simulate_many([Run(plant, r)], RuntimeAdapter(rt))
    (lqi,) = simulate_many([Run(plant, r)], PerPlantController(LQIController))
    if gc.diverged.any():
        return float("inf"), True
    return float(np.mean((gc.y - lqi.y) ** 2) / np.mean(lqi.y**2)), False


@pytest.mark.slow
def test_adapted_tiny_policy_closes_the_loop(tiny_data_dir, tmp_path, mlflow_uri):
    """Tiny: a policy trained 15 epochs on cstr and hydraulic_actuator, adapted to a third."""
    from helpers import train

    out = tmp_path / "train"
    over = tiny_train_overrides(tiny_data_dir, out, mlflow_uri, "trainer.max_epochs=15",
                                "loader.batch_size=32", "dagger.start_epoch=5", "dagger.every=5",
                                "logger.log_model=false")  # fmt: skip
    _, trained = train(compose_cfg(*over))
    common = ("mass_spring_damper", "adapt.batch_size=32", "adapt.epochs=10", "adapt.rounds=2")
    policy = trained["policy_path"]
    _, mean_row = _adapt(policy, tmp_path / "mean", mlflow_uri, *common, "adapt.learn=false",
                         "adapt.init=mean")  # fmt: skip
    record, adapted = _adapt(policy, tmp_path / "row", mlflow_uri, *common)
    start, start_div = _unit_step_errors(mean_row["policy_path"], "mass_spring_damper")
    err, diverged = _unit_step_errors(adapted["policy_path"], "mass_spring_damper")
    assert not diverged
    assert err < 1e-3 and (start_div or err < 0.1 * start), (err, start)
    assert record["closed_loop"]["kept"] < 0.1 * record["closed_loop"]["start"]


@pytest.mark.slow
def test_command_line_adapts_a_registered_version(tiny_data_dir, tmp_path, mlflow_uri):
    """`python adapt.py plant=... policy=models:/<name>/1`: version 2, tagged with its base."""
    from helpers import train

    name = f"tiny-{tmp_path.name}"
    over = tiny_train_overrides(tiny_data_dir, tmp_path / "train", mlflow_uri,
                                f"logger.registered_model_name={name}")  # fmt: skip
    _, trained = train(compose_cfg(*over))
    assert trained["registered_version"] == "1"
    cmd = [
        sys.executable, "adapt.py", "plant=mass_spring_damper", f"policy=models:/{name}/1",
        f"run_dir={tmp_path / 'run'}", f"logger.tracking_uri={mlflow_uri}",
        f"logger.registered_model_name={name}",
        f"logger.artifact_location={tmp_path / 'mlruns'}",
        "adapt.epochs=1", "adapt.rounds=1", *TINY_ADAPT[-3:],
    ]  # fmt: skip
    proc = run_command(cmd, cwd=REPO, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    last = proc.stdout.strip().splitlines()  # Hydra's log: the command's last lines
    assert last[-1].endswith(f"policy written to {tmp_path / 'run' / 'policy.ckpt'}")
    assert (
        "python -m generalist_control.evaluate systems.include=[mass_spring_damper]" in (last[-2])
    )
    mlflow.set_tracking_uri(mlflow_uri)
    version = mlflow.MlflowClient().get_model_version(name, "2")
    assert version.tags["base_version"] == "1"
    assert version.tags["adapted_plant"] == "mass_spring_damper"
    _, meta = load_policy(tmp_path / "run" / "policy.ckpt")
    assert meta["adapted"]["mass_spring_damper"]["base"]["source"] == f"models:/{name}/1"
