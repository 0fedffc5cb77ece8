"""A plant given to the runtime by its model: a plant YAML's path or a model dict."""

from __future__ import annotations

import numpy as np
import pytest
import torch
import yaml

from generalist_control.common.paths import conf_dir
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.bank import fit_model_rows
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.config import plant_from_file
from generalist_control.plants.definition import PlantConfigError
from helpers import net_config
from test_card import card_config

TRAINED = ("cstr", "dc_servo", "unstable")
NEW = "magnetic_levitation"  # never in the bank below


def _meta(names) -> dict:
    plants = [load_plant(n) for n in names]
    return {
        "tags": {p.name: p.tag for p in plants},
        "orders": {p.name: p.order for p in plants},
        "dt": 0.05, "history": 8, "horizon": 3,
        "outputs": {p.name: p.C[0].tolist() for p in plants},
    }  # fmt: skip


@pytest.fixture(scope="module")
def card_policy() -> Policy:
    torch.manual_seed(0)
    policy = Policy(card_config())
    fit_model_rows(policy, [load_plant(n) for n in TRAINED])
    with torch.no_grad():  # a skip that acts, so that the controls depend on the card
        policy.net.skip.gains.weight.normal_(0, 0.1)
    return policy.eval()


def _model_dict(name: str) -> dict:
    p = load_plant(name)
    return {"A": p.A.tolist(), "B": p.B.tolist(), "C": p.C.tolist(), "dt": p.dt,
            "Q": p.Q.tolist(), "R": p.R.tolist(), "name": name}  # fmt: skip


def _controls(rt: PolicyRuntime, plant, steps: int = 25) -> np.ndarray:
    rt.reset(plant)
    x, us = np.zeros(rt.orders[NEW]), []
    for k in range(steps):
        us.append(rt.step(x, 1.0))
        x = x + 0.01 * np.sin(k + np.arange(len(x)))  # any state sequence, the same each time
    return np.array(us)


def test_yaml_path_model_dict_and_plant_give_the_same_controls(card_policy):
    path = conf_dir() / "plants" / f"{NEW}.yaml"
    by_file = _controls(PolicyRuntime(card_policy, _meta(TRAINED)), str(path))
    by_dict = _controls(PolicyRuntime(card_policy, _meta(TRAINED)), _model_dict(NEW))
    by_plant = _controls(PolicyRuntime(card_policy, _meta(TRAINED)), load_plant(NEW))
    # the same plant in the bank from the start, named: what the runtime grows must equal it
    bank = Policy(card_policy.config)
    bank.load_state_dict(card_policy.state_dict())
    fit_model_rows(bank, [load_plant(NEW)], standardise=False)
    by_name = _controls(PolicyRuntime(bank.eval(), _meta([*TRAINED, NEW])), NEW)
    assert np.all(np.isfinite(by_file)) and np.ptp(by_file) > 0
    np.testing.assert_array_equal(by_dict, by_file)
    np.testing.assert_array_equal(by_plant, by_file)
    np.testing.assert_allclose(by_name, by_file, rtol=1e-5, atol=1e-6)


def test_a_plant_yaml_of_its_model_alone_is_named_as_a_model_dict(card_policy, tmp_path):
    model = _model_dict(NEW)
    path = tmp_path / f"{NEW}.yaml"  # no states, input, output, description: the model alone
    path.write_text(
        yaml.safe_dump(
            {
                "dt": model["dt"],
                "A": model["A"],
                "B": model["B"],
                "C": model["C"],
                "lqi": {"Q": model["Q"], "R": model["R"]},
            }
        )
    )
    by_file = _controls(PolicyRuntime(card_policy, _meta(TRAINED)), str(path))
    by_dict = _controls(PolicyRuntime(card_policy, _meta(TRAINED)), model)
    np.testing.assert_array_equal(by_file, by_dict)
    plant = plant_from_file(path)
    assert [s.name for s in plant.states] == ["x1", "x2", "x3"]
    assert (plant.input_signal.name, plant.output_signal.name) == ("u", "y")


def test_a_catalogue_name_still_works_and_a_batch_mixes_names_and_models(card_policy):
    rt = PolicyRuntime(card_policy, _meta(TRAINED))
    rt.reset(["cstr", _model_dict(NEW)])
    assert rt.systems == sorted([*TRAINED, NEW])
    u = rt.step(np.zeros((2, 4)), np.ones(2))
    assert u.shape == (2,) and np.all(np.isfinite(u))


def test_an_unseen_plant_on_the_tag_route_says_where_to_go():
    torch.manual_seed(0)
    policy = Policy(net_config(channels=["integral"], n_tags=25)).eval()
    rt = PolicyRuntime(policy, _meta(TRAINED))
    rt.reset(str(conf_dir() / "plants" / "cstr.yaml"))  # a known name, by its file: kept
    with pytest.raises(ValueError, match=r"model card route.*python adapt\.py plant="):
        rt.reset(str(conf_dir() / "plants" / f"{NEW}.yaml"))
    with pytest.raises(KeyError, match=f"unknown plant '{NEW}'.*reset\\('<plant>.yaml'\\)"):
        rt.reset(NEW)


def test_bad_plants_are_refused_naming_the_problem(card_policy, tmp_path):
    rt = PolicyRuntime(card_policy, _meta(TRAINED))
    not_a_plant = tmp_path / "notes.yaml"
    not_a_plant.write_text(yaml.safe_dump({"title": "a list of things", "items": [1, 2]}))
    with pytest.raises(PlantConfigError, match="notes.yaml is not a plant file"):
        rt.reset(str(not_a_plant))
    with pytest.raises(FileNotFoundError, match="no plant file at"):
        rt.reset(str(tmp_path / "missing.yaml"))
    wrong = {**_model_dict(NEW), "B": [[1.0], [0.0]]}
    with pytest.raises(PlantConfigError, match=r"field 'B' has shape \(2, 1\), expected \(3, 1\)"):
        rt.reset(wrong)
    nan = {**_model_dict(NEW), "A": np.where(np.eye(3) > 0, np.nan, 1.0).tolist()}
    with pytest.raises(PlantConfigError, match="field 'A' contains NaN or inf"):
        rt.reset(nan)
    with pytest.raises(PlantConfigError, match=r"missing \['Q'\]"):
        rt.reset({k: v for k, v in _model_dict(NEW).items() if k != "Q"})
    slow = {**_model_dict(NEW), "dt": 0.1, "name": "slow"}
    with pytest.raises(ValueError, match="sampled at dt = 0.1 s, the policy at 0.05 s"):
        rt.reset(slow)
    assert rt.systems == sorted(TRAINED)  # nothing refused was added
