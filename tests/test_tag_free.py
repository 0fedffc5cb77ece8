"""Issue 13, part 1: a policy without its plant's tag (tag-free switch, tag dropout)."""

from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf, open_dict

from generalist_control.evaluate import run as evaluate_run
from generalist_control.model.identifier import INPUT_GAIN, INPUT_LAGS, TransitionSet
from generalist_control.model.network import GeneralistNetwork, network_config
from generalist_control.model.policy import Policy, load_policy
from generalist_control.training.fit import train
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.setup import model_config
from helpers import compose_cfg, tiny_train_overrides

OPT = {"_target_": "torch.optim.AdamW", "_partial_": True, "lr": 1e-2}


def _window(batch: int = 6, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(batch, 8, 5, generator=g)
    mask = torch.ones(batch, 8, 5)
    ref = torch.randn(batch, 8, generator=g)
    return state, mask, ref


def test_tag_free_network_output_does_not_depend_on_the_tag():
    torch.manual_seed(0)
    state, mask, ref = _window()
    tags_a, tags_b = torch.arange(6), torch.arange(6).flip(0) + 10
    free = GeneralistNetwork(integral=1, linear_skip=1, tag_free=1, history_context=1)
    u_a, _ = free(state, mask, ref, tags_a)
    u_b, _ = free(state, mask, ref, tags_b)
    torch.testing.assert_close(u_a, u_b, rtol=0, atol=0)
    assert free.tag_embedding.num_embeddings == 1
    # the same architecture with its tag: the tag changes the output
    tagged = GeneralistNetwork(integral=1, linear_skip=1)
    assert not torch.allclose(
        tagged(state, mask, ref, tags_a)[0], tagged(state, mask, ref, tags_b)[0]
    )


def test_skip_gain_scale_multiplies_the_skip_path_by_exp_of_its_exponent():
    """u = u_rest + exp(s) u_skip: with s = log 3 the skip path's part triples, the rest not."""
    torch.manual_seed(0)
    net = GeneralistNetwork(
        integral=1, linear_skip=1, tag_free=1, history_context=1, skip_gain_scale=1
    ).eval()
    assert net.skip is not None and net.skip_scale is not None
    torch.nn.init.normal_(net.skip.weight)  # zero at initialisation: give it gains
    args = (*_window(), torch.zeros(6, dtype=torch.long))
    with torch.no_grad():
        u1 = net(*args)[0]  # s = 0 at initialisation: a factor 1
        net.skip_scale.bias.fill_(math.log(3.0))
        u3 = net(*args)[0]
        net.skip.weight.zero_()
        rest = net(*args)[0]
    exponent = 6.0 * math.tanh(math.log(3.0) / 6.0)  # the bounded exponent
    torch.testing.assert_close(u3 - rest, math.exp(exponent) * (u1 - rest), rtol=1e-4, atol=1e-5)
    assert (u1 - rest).abs().max() > 1e-2
    with pytest.raises(ValueError, match="skip_gain_scale scales the skip path's gains"):
        network_config(skip_gain_scale=1)


def test_history_context_makes_the_skip_gains_follow_the_window():
    torch.manual_seed(0)
    net = GeneralistNetwork(integral=1, linear_skip=1, tag_free=1, history_context=1)
    assert net.context is not None and net.skip is not None
    torch.nn.init.normal_(net.skip.weight)  # zero at initialisation: give it gains
    gains = []
    net.skip.register_forward_hook(lambda m, i, o: gains.append(o.detach()))
    for seed in (0, 1):
        net(*_window(seed=seed), torch.zeros(6, dtype=torch.long))
    assert not torch.allclose(gains[0], gains[1])
    # without the context the tag-free skip gains are one row shared by every window
    plain = GeneralistNetwork(integral=1, linear_skip=1, tag_free=1)
    torch.nn.init.normal_(plain.skip.weight)
    gains.clear()
    plain.skip.register_forward_hook(lambda m, i, o: gains.append(o.detach()))
    plain(*_window(seed=0), torch.zeros(6, dtype=torch.long))
    assert torch.equal(gains[0], gains[0][:1].expand_as(gains[0]))


def test_withholding_maps_to_the_unknown_row_and_is_refused_without_one():
    policy = Policy(network_config(unknown_tag=1))
    tag = torch.tensor([0, 3, 24])
    assert torch.equal(policy.network_tags(tag), tag)
    assert torch.equal(
        policy.network_tags(tag, torch.tensor([True, False, True])), torch.tensor([25, 3, 25])
    )
    policy.withhold_tag = True
    assert torch.equal(policy.network_tags(tag), torch.full((3,), 25))
    assert policy.net.tag_embedding.num_embeddings == 26
    plain = Policy(network_config())
    plain.withhold_tag = True
    with pytest.raises(ValueError, match="model.tag_dropout > 0"):
        plain.network_tags(tag)


def test_tag_dropout_withholds_the_share_it_is_set_to_in_training_only():
    lit = ImitationModule(model=network_config(unknown_tag=1), optimizer=OPT, tag_dropout=0.3)
    seen = []
    lit.policy.net.tag_embedding.register_forward_hook(lambda m, i, o: seen.append(i[0].clone()))
    n = 4000
    batch = {
        "state": torch.randn(n, 8, 4),
        "mask": torch.ones(n, 8, 4),
        "ref": torch.randn(n, 8),
        "tag": torch.randint(0, 25, (n,)),
        "target": torch.randn(n, 3),
    }
    lit.train()
    lit._errors(batch)
    share = float((seen[0] == 25).float().mean())
    assert 0.27 < share < 0.33, share
    lit.eval()
    seen.clear()
    lit._errors(batch)
    assert not bool((seen[0] == 25).any())  # validation keeps every tag


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["model.tag_free=true", "model.tag_dropout=0.5"], "tag_free never gives"),
        (["model.tag_free=true", "model.linear_head=true"], "withholds the tag"),
        (["model.tag_dropout=1.0"], r"model.tag_dropout must lie in \[0, 1\)"),
        (["model.control_history=true"], "feeds the skip path's gains"),
    ],
)
def test_contradictory_tag_settings_are_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        model_config(compose_cfg(*overrides))


def test_experiment_tag_free_withholds_the_tag_everywhere():
    cfg = compose_cfg("experiment=tag_free")
    config = model_config(cfg)
    assert config["tag_free"] == 1 and config["history_context"] == 1
    assert config["control_history"] == 1 and model_config(compose_cfg())["control_history"] == 0
    assert config["unknown_tag"] == 0 and cfg.evaluation.withhold_tag
    dropout = model_config(compose_cfg("model.tag_dropout=0.5"))
    assert dropout["unknown_tag"] == 1 and dropout["tag_free"] == 0
    assert model_config(compose_cfg())["unknown_tag"] == 0


def _evaluate_both_ways(data_dir, tmp_path, uri, switch, policy_path) -> dict:
    """The step scenario on cstr and hydraulic_actuator with the tag withheld and given.

    Returns each way's ``metrics.csv``; the withheld run also writes the bar to
    ``tmp_path / "bar"``.
    """
    frames = {}
    for withhold in (True, False):
        reports = tmp_path / f"reports_{withhold}"
        ecfg = compose_cfg(
            *tiny_train_overrides(data_dir, tmp_path / "tf", uri, *switch),
            f"policy={policy_path}",
            f"paths.reports_dir={reports}",
            f"evaluation.withhold_tag={str(withhold).lower()}",
            f"evaluation.tag_free_report={tmp_path / 'bar' if withhold else 'null'}",
            "evaluation.plots=false",
            "systems.include=[cstr,hydraulic_actuator]",
        )
        with open_dict(ecfg):
            ecfg.evaluation.scenarios = OmegaConf.create(
                {"step": {"kind": "step", "amplitude": 1.0, "duration": 5.0}}
            )
            ecfg.evaluation.crazyflie = None
        evaluate_run(ecfg)
        frames[withhold] = pd.read_csv(reports / "metrics.csv")
    return frames


def _ise(frames: dict, controller: str) -> dict:
    return {
        w: f[(f.controller == controller) & (f.metric == "ISE")].value.to_numpy()
        for w, f in frames.items()
    }


@pytest.mark.slow
def test_tiny_tag_dropout_training_evaluates_with_the_tag_withheld(
    tiny_data_dir, tmp_path, mlflow_uri
):
    switch = (
        "experiment=tag_free",
        "model.tag_free=false",
        "model.infer_tag=false",
        "model.transition_models=false",
        "model.transition_input_gain=false",
        "model.transition_input_lag=false",
        "model.transition_input_offset=false",
        "model.identity_noise=0.0",
        "dagger.actuator_lag=0",
        "dagger.actuator_offset=0",
        "model.tag_dropout=0.5",
    )
    cfg = compose_cfg(*tiny_train_overrides(tiny_data_dir, tmp_path / "tf", mlflow_uri, *switch))
    _, objects = train(cfg)
    policy, _ = load_policy(objects["policy_path"])
    assert policy.config["unknown_tag"] == 1 and policy.config["control_history"] == 1
    frames = _evaluate_both_ways(
        tiny_data_dir, tmp_path, mlflow_uri, switch, objects["policy_path"]
    )
    gc, lqi = _ise(frames, "GC"), _ise(frames, "LQI")
    assert (lqi[True] == lqi[False]).all()  # the experts do not depend on the policy's tag
    assert (gc[True] != gc[False]).any()  # the policy does: the tag was really withheld
    bar = json.loads((tmp_path / "bar" / "bar.json").read_text())
    f = frames[True]
    ise = f[(f.scenario == "step") & (f.metric == "ISE")].set_index(["controller", "system"]).value
    assert bar["step_ise_ratio"] == pytest.approx((ise["GC"] / ise["LQI"]).to_dict())
    separation = pd.read_csv(tmp_path / "bar" / "separation.csv")
    assert set(separation.system) == {"cstr", "hydraulic_actuator"}


@pytest.mark.slow
@pytest.mark.parametrize(
    "identifier",
    [
        (
            "data.history=8",
            "model.law_history=0",
            "model.transition_identifier=false",
            "model.transition_models=false",
            "model.transition_input_gain=false",
            "model.transition_input_lag=false",
            "model.transition_input_offset=false",
            "model.identity_noise=0.0",
            "dagger.actuator_lag=0",
            "dagger.actuator_offset=0",
        ),
        (),
        ("model.identity_noise_clean_fit=true",),
    ],
    ids=["lstm", "stage", "stage_clean_fit"],
)
def test_tiny_tag_free_training_keeps_its_controls_and_ignores_the_tag(
    tiny_data_dir, tmp_path, mlflow_uri, identifier
):
    """experiment=tag_free end to end: DAgger after the first epoch, then evaluation.

    With the identity read-out on, so its training and its report table run too; and
    with the stage's transition identifier on a longer window than the law reads.
    """
    switch = ("experiment=tag_free", "model.identity_loss=0.5", *identifier)
    cfg = compose_cfg(*tiny_train_overrides(tiny_data_dir, tmp_path / "tf", mlflow_uri, *switch))
    _, objects = train(cfg)
    policy, _ = load_policy(objects["policy_path"])
    assert policy.config["tag_free"] == policy.config["control_history"] == 1
    assert policy.net.identifier is not None and policy.net.state_encoder_1[0].in_features == 5
    lstm = "model.transition_identifier=false" in identifier
    kind = torch.nn.LSTM if lstm else TransitionSet
    assert isinstance(policy.net.identifier, kind)
    if not lstm:  # the stage's plant models: trained away from their zero start
        assert policy.net.identifier.models.params.weight.abs().max() > 0
        assert policy.net.identifier.models.input_gain == INPUT_GAIN  # the stage's fitted gain
    fitted = not lstm  # the stage fits a lag and an offset, under noise and actuator draws
    if fitted:
        models = policy.net.identifier.models
        assert models.lags == INPUT_LAGS and models.offset
    # the training noise reached the identifier of the trained network (never stored)
    trained = objects["trainer"].lightning_module.policy.net
    assert trained.identity_noise == (0.02 if fitted else 0.0) and policy.net.identity_noise == 0
    clean = "model.identity_noise_clean_fit=true" in identifier
    assert trained.identity_clean_fit == clean and not policy.net.identity_clean_fit
    assert (policy.config["history"], policy.config["law_history"]) == (
        (8, 0) if lstm else (24, 8)
    )
    (cb,) = [c for c in objects["trainer"].callbacks if type(c).__name__ == "DAggerCallback"]
    assert cb.done == 1 and cb.history[0]["windows"] > 0  # a round after the first epoch
    assert (cb.actuator_lag, cb.actuator_offset) == ((1.0, 0.3) if fitted else (0.0, 0.0))
    frames = _evaluate_both_ways(
        tiny_data_dir, tmp_path, mlflow_uri, switch, objects["policy_path"]
    )
    gc = _ise(frames, "GC")
    assert len(gc[True]) == 2 and (gc[True] == gc[False]).all()  # the tag changes nothing
    bar = json.loads((tmp_path / "bar" / "bar.json").read_text())
    assert bar["step_ise_ratio"]
    left = pd.read_csv(tmp_path / "bar" / "departures.csv")
    diverged = frames[True].query("controller == 'GC' and metric == 'diverged' and value > 0")
    assert len(left) == len(diverged) == bar["departures"]["runs"]  # one row per diverged run
    handover = pd.read_csv(tmp_path / "bar" / "handover.csv")
    assert sorted(set(handover.handover_samples)) == [0, 1, 2, 5, 10, 20, 40]
    start = handover[handover.handover_samples == 0].set_index("system")
    for system, ratio in bar["step_ise_ratio"].items():  # N = 0: the evaluation's own GC run
        if start.diverged[system] == 0:
            assert start.ise_ratio[system] == pytest.approx(ratio, rel=1e-9)
    assert set(bar["handover"]) == {"0", "1", "2", "5", "10", "20", "40"}
    named = pd.read_csv(tmp_path / "bar" / "identity.csv")
    assert set(named.system) == {"cstr", "hydraulic_actuator"} and len(named) == 10
    assert named.p_true.between(0, 1).all() and (named.p_guess >= named.p_true - 1e-12).all()
    assert bar["identity"]["0.1"]["plants"] == 2


def test_withholding_from_a_tagged_policy_is_refused_with_the_fix(tmp_path):
    from generalist_control.model.policy import save_policy
    from helpers import policy_meta

    path = save_policy(tmp_path / "p.ckpt", Policy(network_config()), policy_meta(["cstr"]))
    cfg = compose_cfg(
        f"policy={path}", "evaluation.withhold_tag=true", f"paths.reports_dir={tmp_path / 'r'}"
    )
    with pytest.raises(ValueError, match="experiment=tag_free"):
        evaluate_run(cfg)


def _evaluate_given(tmp_path, path, given: bool) -> pd.DataFrame:
    reports = tmp_path / f"r_{given}"
    cfg = compose_cfg(
        f"policy={path}",
        "experiment=tag_free",
        f"evaluation.identity_given={str(given).lower()}",
        f"paths.reports_dir={reports}",
        f"evaluation.tag_free_report={tmp_path / f'bar_{given}'}",
        "evaluation.plots=false",
        "evaluation.handover_samples=[]",
        "evaluation.gain_samples=null",
        "systems.include=[cstr,two_tank]",
        f"logger.tracking_uri=sqlite:///{tmp_path / 'mlflow.db'}",
    )
    with open_dict(cfg):
        cfg.evaluation.scenarios = OmegaConf.create(
            {"step": {"kind": "step", "amplitude": 1.0, "duration": 2.0}}
        )
        cfg.evaluation.crazyflie = None
    evaluate_run(cfg)
    frame = pd.read_csv(reports / "metrics.csv")
    return frame[frame.controller == "GC"].set_index(["system", "metric", "run"]).value


def test_identity_given_gives_the_inferring_network_the_true_plant_s_row(tmp_path):
    """A head sure of cstr: given or inferred, cstr's runs are the same; two_tank's differ."""
    from generalist_control.model.policy import save_policy
    from generalist_control.plants.catalog import load_plant
    from helpers import policy_meta

    torch.manual_seed(0)
    policy = Policy(_identity_config(infer_tag=1)).eval()
    with torch.no_grad():
        policy.net.skip.weight.normal_(std=0.01)
        policy.net.identity.weight.zero_()
        policy.net.identity.bias.fill_(-1e4)
        policy.net.identity.bias[load_plant("cstr").tag] = 0.0
    path = save_policy(tmp_path / "p.ckpt", policy, policy_meta(["cstr", "two_tank"]))
    inferred, given = (_evaluate_given(tmp_path, path, g) for g in (False, True))
    pd.testing.assert_series_equal(inferred.loc["cstr"], given.loc["cstr"])
    assert not np.allclose(inferred.loc["two_tank"], given.loc["two_tank"], equal_nan=True)
    bars = [json.loads((tmp_path / f"bar_{g}" / "bar.json").read_text()) for g in (False, True)]
    assert "identity_given" not in bars[0]
    assert bars[1]["identity_given"] is True and bars[1]["met"] is False
    # logged apart from the policy's own evaluation
    import mlflow

    mlflow.set_tracking_uri(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = mlflow.search_runs(search_all_experiments=True, output_format="list")
    key = {g: f"eval{'_identity_given' if g else ''}/diverged/GC" for g in (False, True)}
    for g, frame in ((False, inferred), (True, given)):
        (run,) = (r for r in runs if key[g] in r.data.metrics)
        assert key[not g] not in run.data.metrics
        assert run.data.metrics[key[g]] == frame.loc[:, "diverged", :].sum()
    plain = save_policy(tmp_path / "q.ckpt", Policy(_identity_config()), policy_meta(["cstr"]))
    with pytest.raises(ValueError, match="does not infer its plant"):
        _evaluate_given(tmp_path, plain, True)


def _long(rows):
    return pd.DataFrame(
        rows, columns=["system", "scenario", "controller", "run", "metric", "value"]
    )


def test_tag_free_bar_counts_ratios_and_divergence_by_hand():
    from generalist_control.evaluation.tag_free import tag_free_bar

    rows = []
    for system, gc, lqi in (("a", 1.0, 1.0), ("b", 2.6, 2.0), ("c", 1.2, 1.0)):
        rows += [(system, "step", "GC", 0, "ISE", gc), (system, "step", "LQI", 0, "ISE", lqi)]
        rows += [(system, "step", "GC", 0, "diverged", 0.0)]
    rows += [("c", "sine", "GC", 0, "diverged", 1.0), ("a", "sine", "LQI", 0, "diverged", 1.0)]
    bar = tag_free_bar(_long(rows), ise_ratio=1.25, min_plants=2)
    assert bar["step_ise_ratio"] == pytest.approx({"a": 1.0, "b": 1.3, "c": 1.2})
    assert bar["missing"] == ["b"] and bar["passed"] == 2 and bar["step_ise_ratio_met"]
    assert bar["diverged"] == ["c/sine"]  # LQI's divergence is not GC's
    assert not bar["no_divergence"] and not bar["met"]
    assert not tag_free_bar(_long(rows), min_plants=3)["step_ise_ratio_met"]


def test_separation_finds_a_twin_and_parts_plants_of_another_order_at_once():
    import dataclasses

    from generalist_control.evaluation.separation import separation_table
    from generalist_control.plants.catalog import load_plant

    cstr, hyd = load_plant("cstr"), load_plant("hydraulic_actuator")
    twin = dataclasses.replace(cstr, name="cstr_twin")
    policy = Policy(network_config(integral=1, window_scale=1))
    table = separation_table(policy, [cstr, twin, hyd], duration=1.0).set_index("system")
    assert table.loc["cstr", "nearest"] == "cstr_twin"
    assert table.loc["cstr", "input_gap"] == 0 and table.loc["cstr", "control_gap"] == 0
    assert table.loc["cstr", "separation_time"] == float("inf")
    assert table.loc["hydraulic_actuator", "separation_time"] == pytest.approx(cstr.dt)


def _traj(y, r, diverged):
    from generalist_control.simulation.simulate import Trajectory

    y, r = np.atleast_2d(y), np.atleast_2d(r)
    t = np.arange(r.shape[1] + 1) * 0.05
    x = y[..., None]
    return Trajectory(t=t, x=x, u=np.zeros_like(r), r=r, y=y, diverged=np.asarray(diverged))


def test_departures_place_each_diverged_run_on_its_reference_level_by_hand():
    """Level changes at samples 20 and 40; GC leaves at 46 (level 2) or at 6 (level 0)."""
    from generalist_control.evaluation.departures import COLUMNS, departure_summary
    from generalist_control.evaluation.departures import departure_table as table

    r = np.repeat([1.0, 3.0, 5.0], 20)
    lqi_y = np.append(r - 1.0, r[-1] - 1.0)  # the expert's tracking error: 1 throughout
    late, early, fine = lqi_y.copy(), lqi_y.copy(), lqi_y.copy()
    late[47:] = 1e7
    late[46] = 5.0 + 3.5  # error 3.5 > 3 x 1 first at sample 46 (level 2, 6 samples in)
    early[6:] = np.nan  # a non-finite output counts
    sine = np.sin(np.arange(60) * 0.3)
    sine_lqi = np.append(sine - 0.1, 0.0)
    sine_gc = sine_lqi.copy()
    sine_gc[30:] = 50.0
    trajs = {
        "staircase": {
            "GC": {"p": _traj(np.stack([late, early, fine]), np.stack([r] * 3), [1, 1, 0])},
            "LQI": {"p": _traj(np.stack([lqi_y] * 3), np.stack([r] * 3), [0, 0, 0])},
        },
        "sine": {
            "GC": {"q": _traj(sine_gc, sine, [1])},
            "LQI": {"q": _traj(sine_lqi, sine, [0])},
        },
        "step": {"GC": {"p": _traj(lqi_y, r, [1])}},  # no LQI runs: left out
    }
    got = table(trajs)
    assert list(got.columns) == COLUMNS
    rows = {(s, run): row for _, s, run, *row in got.itertuples(index=False, name=None)}
    assert set(rows) == {("staircase", 0), ("staircase", 1), ("sine", 0)}
    np.testing.assert_allclose(rows["staircase", 0][:3], [46 * 0.05, 2, 6 * 0.05])
    np.testing.assert_allclose(rows["staircase", 1][:3], [6 * 0.05, 0, 6 * 0.05])
    assert rows["sine", 0][0] == pytest.approx(30 * 0.05)
    assert np.isnan(rows["sine", 0][1]) and np.isnan(rows["sine", 0][2])
    assert departure_summary(got) == {
        "runs": 3,
        "on_first_level": 1,
        "after_a_later_change": 1,
        "continuous_reference": 1,
        "median_t_leave_s": pytest.approx(30 * 0.05),
    }
    # a run lost through another state: its output stays within 3x, its state freezes at 30
    stuck = lqi_y + 0.001 * np.arange(61)
    stuck[30:] = stuck[30]
    other = {"staircase": {"GC": {"p": _traj(stuck, r, [1])}, "LQI": {"p": _traj(lqi_y, r, [0])}}}
    np.testing.assert_allclose(table(other).iloc[0, 3:], [30 * 0.05, 1, 10 * 0.05])
    # a looser factor lets the error of 3.5 pass: the late run leaves one sample later
    assert table(trajs, factor=4.0).set_index(["scenario", "run"]).loc[
        ("staircase", 0), "t_leave"
    ] == pytest.approx(47 * 0.05)


def _identity_config(**extra: int) -> dict[str, int]:
    """A tag-free network with the identifier and the identity head."""
    switches = ("integral", "linear_skip", "tag_free", "history_context", "control_history")
    return network_config(**dict.fromkeys(switches, 1), identity_head=1, **extra)


def _identity_batch(n: int = 64, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "state": torch.randn(n, 8, 6, generator=g),
        "mask": torch.ones(n, 8, 6),
        "ref": torch.randn(n, 8, generator=g),
        "tag": torch.randint(0, 25, (n,), generator=g),
        "target": torch.randn(n, 3, generator=g),
    }


def test_identity_loss_adds_the_cross_entropy_of_the_plant_read_out():
    """Training loss = imitation MSE + w * CE(identity logits, tag), recomputed by hand."""
    cfg = _identity_config()
    torch.manual_seed(0)
    lit = ImitationModule(model=cfg, optimizer=OPT, identity_loss=0.5).eval()
    batch = _identity_batch()
    with torch.no_grad():
        loss = lit.training_step(batch, 0)
        p = lit.policy
        x, m, r, _, s = p.network_inputs(batch["state"], batch["mask"], batch["ref"], batch["tag"])
        u, _, code = p.net.forward_code(x, m, r, batch["tag"])
        assert code is not None and p.net.identity is not None
        mse = (
            (u - p.normaliser.normalise_controls(batch["target"], batch["tag"]) / s) ** 2
        ).mean()
        logits = code @ p.net.identity.weight.T + p.net.identity.bias
        ce = -torch.log_softmax(logits, 1)[torch.arange(64), batch["tag"]].mean()
    torch.testing.assert_close(loss, mse + 0.5 * ce)
    # the read-out is a training signal only: the control does not depend on the tag
    other = {**batch, "tag": (batch["tag"] + 7) % 25}
    with torch.no_grad():
        u_other = p.net.forward_code(x, m, r, other["tag"])[0]
    torch.testing.assert_close(u, u_other, rtol=0, atol=0)


def test_identity_loss_trains_the_context_to_name_the_plant():
    """Windows whose history differs by plant: the read-out learns to tell them apart."""
    cfg = _identity_config()
    torch.manual_seed(0)
    lit = ImitationModule(model=cfg, optimizer=OPT, identity_loss=1.0)
    batch = _identity_batch(n=200)
    batch["tag"] = torch.randint(0, 2, (200,), generator=torch.Generator().manual_seed(1))
    batch["state"][:, :, 0] += 3.0 * batch["tag"].unsqueeze(1)  # plant 1's first state is offset
    opt = torch.optim.Adam(lit.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        lit.training_step(batch, 0).backward()
        opt.step()
    with torch.no_grad():
        _, logits, _ = lit._errors(batch)
    assert logits is not None
    assert float((logits.argmax(1) == batch["tag"]).float().mean()) > 0.95


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["model.identity_loss=-0.1"], "finite number >= 0"),
        (["model.identity_loss=0.5"], "reads the plant from the skip gains' context"),
    ],
)
def test_bad_identity_loss_is_refused(overrides, message):
    with pytest.raises(ValueError, match=message):
        model_config(compose_cfg(*overrides))


def test_identity_head_is_built_from_the_weight_only():
    assert model_config(compose_cfg())["identity_head"] == 0
    stage = model_config(compose_cfg("experiment=tag_free"))
    assert stage["identity_head"] == stage["infer_tag"] == 1
    off = ("experiment=tag_free", "model.identity_loss=0", "model.infer_tag=false")
    off += ("model.transition_models=false", "model.transition_input_gain=false")
    off += ("model.transition_input_lag=false", "model.transition_input_offset=false")
    assert model_config(compose_cfg(*off))["identity_head"] == 0
    with pytest.raises(ValueError, match="no identity head"):
        GeneralistNetwork().identity_logits(torch.zeros(2, 32))


def test_identity_table_reads_the_head_on_each_plant_s_expert_step():
    """A head whose output is its bias alone: p_true is the softmax of the bias over the
    plants, at each of the times asked; a policy without the head is refused."""
    from generalist_control.evaluation.identity import identity_table
    from generalist_control.plants.catalog import load_plant

    plants = [load_plant(n) for n in ("cstr", "two_tank", "hydraulic_actuator")]
    cfg = _identity_config()
    policy = Policy(cfg).eval()
    head = policy.net.identity
    assert head is not None
    with torch.no_grad():
        head.weight.zero_()
        head.bias.zero_()
        head.bias[plants[1].tag] = 2.0
    table = identity_table(policy, plants, times=(0.1, 0.5))
    assert list(table.time.unique()) == pytest.approx([0.1, 0.5])
    p_two_tank = math.exp(2.0) / (math.exp(2.0) + 2.0)
    for name, group in table.groupby("system"):
        expected = p_two_tank if name == "two_tank" else 1.0 / (math.exp(2.0) + 2.0)
        assert group.p_true.to_numpy() == pytest.approx([expected] * 2)
        assert (group.guess == "two_tank").all()
    with pytest.raises(ValueError, match="no identity head"):
        identity_table(Policy(network_config(linear_skip=1, integral=1)), plants)


def test_infer_tag_weighs_the_plants_rows_by_the_identity_head_and_ignores_the_tag():
    cfg = _identity_config(infer_tag=1)
    torch.manual_seed(0)
    net = GeneralistNetwork(**cfg).eval()
    assert net.tag_embedding.num_embeddings == 25 and net.identity is not None
    torch.nn.init.normal_(net.skip.weight)  # zero at initialisation: give it gains
    batch = _identity_batch(n=6)  # state, integral and previous control: 6 channels
    state, mask, ref = batch["state"], batch["mask"], batch["ref"]
    tags_a, tags_b = torch.arange(6), torch.arange(6).flip(0) + 10
    with torch.no_grad():
        u_a, _, ident = net.forward_code(state, mask, ref, tags_a)
        torch.testing.assert_close(u_a, net(state, mask, ref, tags_b)[0], rtol=0, atol=0)
        # the embedding is the softmax-weighted rows of the head's logits on the identifier
        weights = torch.softmax(ident @ net.identity.weight.T + net.identity.bias, dim=1)
        torch.testing.assert_close(
            net.embedding(tags_a, ident), weights @ net.tag_embedding.weight
        )
        # a head sure of plant 3: the rows of plant 3 exactly; of plant 7: another control
        net.identity.weight.zero_()
        net.identity.bias.fill_(-1e4)
        net.identity.bias[3] = 0.0
        torch.testing.assert_close(
            net.embedding(tags_a, ident), net.tag_embedding.weight[3].expand(6, -1)
        )
        u_3 = net(state, mask, ref, tags_a)[0]
        net.identity.bias[[3, 7]] = torch.tensor([-1e4, 0.0])
        assert not torch.allclose(u_3, net(state, mask, ref, tags_a)[0])
        # the diagnostic evaluation.identity_given: each sample gets its own tag's row
        net.identity_given = True
        torch.testing.assert_close(net.embedding(tags_a, ident), net.tag_embedding(tags_a))
        assert not torch.allclose(
            net(state, mask, ref, tags_a)[0], net(state, mask, ref, tags_b)[0]
        )


def test_infer_tag_without_what_it_needs_is_refused():
    with pytest.raises(ValueError, match="model.infer_tag infers the tag"):
        network_config(integral=1, linear_skip=1, history_context=1, infer_tag=1)
    with pytest.raises(ValueError, match="model.infer_tag infers the tag"):
        model_config(compose_cfg("experiment=tag_free", "model.identity_loss=0"))


def test_identity_trace_reads_the_head_on_the_runtime_s_own_windows():
    """Before the hand-over the runtime's windows are the expert's closed loop: the traced
    probabilities there equal the head's on the windows the window builder cuts from the
    expert's own step (identity_table), sample by sample."""
    from generalist_control.deploy.runtime import PolicyRuntime
    from generalist_control.evaluation.identity import (
        identity_summary,
        identity_table,
        identity_trace,
    )
    from generalist_control.plants.catalog import load_plant
    from helpers import policy_meta

    names = ["cstr", "two_tank"]
    plants = [load_plant(n) for n in names]
    torch.manual_seed(0)
    policy = Policy(_identity_config(infer_tag=1)).eval()
    with torch.no_grad():
        torch.nn.init.normal_(policy.net.identity.weight)  # a head that tells windows apart
    spec = {"kind": "step", "amplitude": 1.0, "duration": 1.0}
    trace = identity_trace(PolicyRuntime(policy, policy_meta(names)), plants, spec, [0, 5])
    assert set(trace.handover_samples) == {0, 5}
    part = trace[trace.handover_samples == 5]
    assert len(part) == 2 * 20 and set(part.system) == set(names)
    table = identity_table(policy, plants, times=(0.05, 0.1, 0.2))
    expert = part.assign(time=part.time.round(6)).set_index(["system", "time"]).p_true
    reference = table.assign(time=table.time.round(6)).set_index(["system", "time"]).p_true
    assert len(set(reference.round(6))) > 2  # the head's answers differ by plant and time
    for key, value in reference.items():
        assert expert[key] == pytest.approx(value, rel=1e-4)
    summary = identity_summary(table, trace)
    assert set(summary) == {"0.05", "0.1", "0.2", "own_from_0", "own_from_5"}
    assert set(summary["own_from_5"]) == set(names)
