"""Settings that used to get a weak answer get a clear one (issue 36, item 5).

``systems.include=[]`` is refused (it named every plant); ``evaluation.variants.range`` must
be a number in (0, 1) (5 drew sign-flipped variants, 0 became 0.25); ``summary.json`` says
which policy it describes; an Optuna study name must be a plain name (``../x`` wrote its
trials outside the project).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.data.variants import variants_config
from generalist_control.evaluate import run as evaluate_run
from generalist_control.evaluation.variants import draw_eval_variants
from generalist_control.generate import run as generate_run
from generalist_control.model.policy import save_policy
from generalist_control.plants.catalog import load_plant, plants_from_config
from generalist_control.plants.plant import PlantConfigError
from generalist_control.plants.variants import DEFAULT_RANGE, variant_range
from generalist_control.simulation.lqi import LQIGains, design_lqi
from generalist_control.tune import run as study_run
from helpers import compose_cfg, lqi_law_policy

# --- systems.include=[] ------------------------------------------------------------------


def test_an_empty_include_list_names_no_plant_and_is_refused(tmp_path):
    cfg = compose_cfg("systems.include=[]", f"paths.data_dir={tmp_path / 'demos'}")
    with pytest.raises(PlantConfigError, match=r"systems\.include=\[\] names no plant.*drop"):
        plants_from_config(cfg.systems)
    with pytest.raises(PlantConfigError, match=r"name plants, e\.g\. systems\.include=\[cstr\]"):
        generate_run(cfg)
    assert list(tmp_path.iterdir()) == []  # refused before anything was written
    everything = plants_from_config(compose_cfg().systems)  # the key left out: every plant
    assert len(everything) == len(compose_cfg().systems.plants) >= 25


# --- evaluation.variants.range -----------------------------------------------------------


@pytest.mark.parametrize("value", [5, 1.0, 0, 0.0, -0.1, "wide", True])
def test_a_variant_range_outside_zero_one_is_refused_naming_the_key(value):
    with pytest.raises(ValueError, match=r"evaluation\.variants\.range = .* must be a number"):
        draw_eval_variants([load_plant("cstr")], {"count": 6, "seed": 1, "range": value}, 100)
    with pytest.raises(ValueError, match=r"data\.variants\.range = .* in \(0, 1\)"):
        variants_config({"variants": {"enabled": True, "range": value}})


def test_a_range_left_out_is_the_default_and_a_valid_one_is_kept():
    assert variant_range(None, "evaluation.variants.range") == DEFAULT_RANGE == 0.25
    assert variant_range(0.4, "evaluation.variants.range") == 0.4
    assert variants_config({"variants": {"enabled": True, "range": 0.1}})["range"] == 0.1


# --- summary.json names its policy ---------------------------------------------------------


def _half(plant) -> LQIGains:
    g = design_lqi(plant)
    return LQIGains(Kx=g.Kx / 2, Ki=g.Ki / 2, P=g.P, poles=g.poles)


def _evaluate(policy: Path, reports: Path, tmp_path: Path, uri: str) -> dict:
    overrides = [
        f"policy={policy}",
        "systems.include=[cstr]",
        f"paths.reports_dir={reports}",
        "~evaluation.scenarios",
        "+evaluation.scenarios={step: {kind: step, amplitude: 1.0, duration: 3.0}}",
        "evaluation.setpoint=null",
        "evaluation.plots=false",
        "evaluation.backend=torch",
        f"logger.tracking_uri={uri}",
        f"logger.experiment_name={tmp_path.name}",
    ]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        evaluate_run(compose("config", overrides=overrides))
    return json.loads((reports / "summary.json").read_text())


def test_two_evaluations_into_one_folder_each_say_which_policy(tmp_path, mlflow_uri):
    paths = {}
    for name, gains in (("full", design_lqi), ("half", _half)):
        pol, meta = lqi_law_policy(["cstr"], gains)
        meta = {**meta, "mlflow_run_id": "0123abcd"} if name == "half" else meta
        paths[name] = save_policy(tmp_path / name / "policy.ckpt", pol, meta)
    reports = tmp_path / "reports"
    first = _evaluate(paths["full"], reports, tmp_path, mlflow_uri)
    second = _evaluate(paths["half"], reports, tmp_path, mlflow_uri)
    for summary, name in ((first, "full"), (second, "half")):
        digest = hashlib.sha256(paths[name].read_bytes()).hexdigest()
        assert summary["policy"] == {
            "source": str(paths[name]),
            "mlflow_run_id": "0123abcd" if name == "half" else None,
            "sha256": f"sha256:{digest}",
        }
    assert first["policy"]["sha256"] != second["policy"]["sha256"]
    assert {"diverged", "ratios", "tracking", "anti_windup", "quality_bar"} <= set(second)


# --- hparams_search.study_name -------------------------------------------------------------


@pytest.mark.parametrize("name", ["../escape", "a/b", "..", ".hidden", "a\\b", "", "x'y"])
def test_a_study_name_that_is_not_a_plain_name_is_refused(tmp_path, name):
    db = tmp_path / "optuna.db"
    overrides = [
        f"hparams_search.storage=sqlite:///{db}",
        f"hparams_search.trials_dir={tmp_path / 'trials'}",
        "hparams_search.n_trials=0",
    ]
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("tune", overrides=overrides)
    cfg.hparams_search.study_name = name  # as a config file may hold it
    with pytest.raises(ValueError, match=r"study_name = .* is not a plain name.*e\.g\."):
        study_run(cfg)
    assert list(tmp_path.iterdir()) == []  # refused before the storage was opened
