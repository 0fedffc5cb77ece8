"""DAgger: expert labels on visited states, checked against the expert's own trajectories."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from generalist_control.data.windows import build_windows
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import simulate
from generalist_control.training.datamodule import WindowTensors
from generalist_control.training.labeller import (
    ExpertLabeller,
    bumpless_integrator,
    expert_plans,
)
from generalist_control.training.sampler import (
    InTurn,
    MixedController,
    RolloutSampler,
    WorstFirst,
    run_rollouts,
)
from generalist_control.training.settings import (
    DaggerSettings,
    LabellerSettings,
    RolloutData,
    SamplerSettings,
    VariantSettings,
)
from helpers import config_section, lqi_law_policy, net_config


def _steps(amplitudes, steps):
    """Step rollouts from rest: references (B, steps), no initial states."""
    return (np.repeat(np.asarray(amplitudes, float)[:, None], steps, axis=1), None)


def aggregate(plants, runtime, beta, specs, bounds, steps, history, horizon, channels=(),
              noise=None, seed=0, actuator=None):  # fmt: skip
    """One DAgger round: the sampler's loop, then the labeller (specs: amplitudes per plant)."""
    specs = [s if isinstance(s, tuple) else _steps(s, steps) for s in specs]
    rollouts = run_rollouts(plants, specs, runtime, beta, noise, seed, actuator)
    labeller = ExpertLabeller(
        config_section(LabellerSettings, "dagger.labeller"), history, horizon, channels
    )
    return labeller.label(rollouts, bounds)


def _meta(*plants):
    return {"tags": {p.name: p.tag for p in plants}, "orders": {p.name: p.order for p in plants},
            "dt": plants[0].dt, "history": 8, "horizon": 3}  # fmt: skip


@pytest.mark.parametrize("name", ["magnetic_levitation", "two_tank", "two_mass_spring"])
def test_pure_expert_round_reproduces_the_demonstration_windows(name):
    """With beta = 1 the expert's plan at each visited state is what it then did."""
    plant = load_plant(name)
    amps = np.array([1.0, -2.5]) * plant.amplitude_scale
    steps, big = 60, np.full(plant.order, np.inf)
    windows, counts = aggregate([plant], None, 1.0, [amps], {name: big}, steps, 8, 3)
    tr = simulate(plant, LQIController(plant), np.repeat(amps[:, None], steps, axis=1))
    ref = build_windows(
        pad_states(tr.x[:, :steps]), tr.r, tr.u, np.full(2, plant.tag), np.full(2, plant.order),
        8, 3,
    )  # fmt: skip
    assert counts == {name: len(ref)}
    np.testing.assert_allclose(windows.target, ref.target, rtol=1e-6, atol=1e-7)
    np.testing.assert_array_equal(windows.state, ref.state)
    np.testing.assert_array_equal(windows.ref, ref.ref)


def test_rounds_for_an_integrating_policy_label_the_augmented_state_it_sees():
    """With the integral channel the label is the LQI law at the window's own [x; z]."""
    plant = load_plant("cstr")
    g = design_lqi(plant)
    torch.manual_seed(0)
    policy = Policy(net_config(hidden=8, experts=1, channels=["integral"])).eval()
    runtime = PolicyRuntime(policy, _meta(plant))
    big = {plant.name: np.full(plant.order, np.inf)}
    amps = [np.array([1.0, -2.0])]
    w, _ = aggregate([plant], runtime, 0.5, amps, big, 40, 8, 3, ["integral"])
    assert w.state.shape[1:] == (8, 5)
    newest = w.state[:, -1].astype(float)
    law = -(newest[:, : plant.order] @ g.Kx) - g.Ki * newest[:, 4]
    np.testing.assert_allclose(w.target[:, 0], law, rtol=1e-4, atol=1e-5)
    assert np.abs(newest[:, 4]).max() > 0.1  # the policy's rollouts moved the integrator


def test_rounds_for_a_previous_control_policy_carry_the_executed_controls():
    """With the previous-control channel the last channel is the mixed control executed before.

    The rollout's policy saw those same windows: the executed control is ``0.5 u_expert +
    0.5 u_policy``, and ``u_policy`` recomputed by the network from the aggregated windows
    (previous control included) is the one the rollout blended.
    """
    from generalist_control.deploy.export import backend
    from generalist_control.simulation.simulate import Run, simulate_many

    plant = load_plant("hydraulic_actuator")
    torch.manual_seed(0)
    channels = ["integral", "previous_control"]
    config = net_config(hidden=8, experts=1, channels=channels, plant="inferred",
                        skip="context", models=None)  # fmt: skip
    policy = Policy(config).eval()
    with torch.no_grad():  # the skip path's gains start at zero: give them weight, so that
        policy.net.skip.gains.weight.normal_(0.0, 0.3)  # the previous control reaches it
    meta = _meta(plant)
    big = {plant.name: np.full(plant.order, np.inf)}
    amps = np.array([1.0, -2.0])
    args = ([plant], PolicyRuntime(policy, meta), 0.5, [amps], big, 40, 8, 3)
    w, _ = aggregate(*args, channels)
    assert w.state.shape[1:] == (8, 6)
    refs = np.repeat(amps[:, None], 40, axis=1)
    tr = simulate_many([Run(plant, refs)], MixedController(PolicyRuntime(policy, meta), 0.5))[0]
    executed = np.concatenate([np.zeros((2, 1)), tr.u[:, :-1]], axis=1)[:, : 40 - 3 + 1]
    np.testing.assert_allclose(w.state[:, -1, 5], executed.reshape(-1), rtol=1e-6, atol=1e-7)
    assert np.abs(executed).max() > 0.1
    run = backend(policy, "torch")
    own = w.state.copy()
    own[:, :, 5] *= 2.0
    assert np.abs(run(own, w.mask, w.ref, w.tag) - run(w.state, w.mask, w.ref, w.tag)).max() > 1e-2
    u_policy = run(w.state, w.mask, w.ref, w.tag)[:, 0]
    blended = 0.5 * w.target[:, 0] + 0.5 * u_policy  # the expert's law, the network's answer
    np.testing.assert_allclose(blended, tr.u[:, :38].reshape(-1), rtol=1e-4, atol=1e-5)
    assert np.abs(u_policy - w.target[:, 0]).max() > 0.1  # the two differ: a real blend


def test_the_expert_s_share_decays_by_round_and_the_schedule_runs_when_due():
    """beta_i = beta * beta_decay ** i; rounds after start_epoch, then every `every` epochs."""
    settings = config_section(
        DaggerSettings, "dagger", start_epoch=6, every=4, rounds=5, beta=0.5, beta_decay=0.5
    )
    assert [settings.beta_at(i) for i in range(4)] == [0.5, 0.25, 0.125, 0.0625]
    from generalist_control.training.callbacks import DAggerCallback

    cb = DAggerCallback(None, None, settings)  # type: ignore[arg-type]
    due = []
    for epochs in range(1, 40):
        if cb.due(epochs):
            due.append(epochs)
            cb.done += 1
    assert due == [6, 10, 14, 18, 22]


def test_a_round_executes_the_expert_s_share_of_its_round():
    """Round i's rollouts blend beta_i of the expert's control with the policy's."""
    from types import SimpleNamespace

    from generalist_control.training.callbacks import DAggerCallback

    plant = load_plant("dc_servo")
    torch.manual_seed(0)
    policy = Policy(net_config(hidden=8, experts=1))
    seen = []

    class Sampler:
        plants = [plant]

        def run(self, round_index, runtime, beta):
            seen.append((round_index, beta))
            return run_rollouts([plant], [_steps([1.0], 20)], runtime, beta)

    labeller = ExpertLabeller(LabellerSettings(bound_factor=1e9), 8, 3, ())
    first, _ = aggregate(
        [plant], None, 1.0, [[1.0]], {plant.name: np.full(plant.order, np.inf)}, 20, 8, 3
    )
    dm = SimpleNamespace(meta=lambda: _meta(plant), train_set=WindowTensors(first))
    trainer = SimpleNamespace(datamodule=dm, callbacks=[], should_stop=True, current_epoch=0)
    module = SimpleNamespace(policy=policy, log=lambda *a, **k: None)
    settings = config_section(
        DaggerSettings, "dagger", start_epoch=1, every=1, rounds=3, beta=0.8, beta_decay=0.25
    )
    cb = DAggerCallback(Sampler(), labeller, settings)  # type: ignore[arg-type]
    for epoch in range(4):
        trainer.current_epoch = epoch
        cb.on_train_epoch_end(trainer, module)  # type: ignore[arg-type]
    assert seen == [(0, 0.8), (1, 0.2), (2, 0.05)]
    assert [r["beta"] for r in cb.history] == [0.8, 0.2, 0.05]
    assert trainer.should_stop is False and policy.training  # training mode restored


def test_expert_plan_first_control_is_the_lqi_law_at_any_state():
    plant = load_plant("unstable")
    g = design_lqi(plant)
    rng = np.random.default_rng(0)
    x = rng.normal(size=(3, 5, plant.order))
    z = rng.normal(size=(3, 5))
    r = rng.normal(size=(3, 5))
    plans = expert_plans(plant, x, z, r, 3)
    np.testing.assert_allclose(plans[..., 0], -(x @ g.Kx) - g.Ki * z, rtol=1e-12)
    # second control: one ZOH step of the plant and one Euler step of the integrator
    from generalist_control.simulation.simulate import discretise

    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    x1 = x @ Ad.T + plans[..., :1] * Bd[:, 0]
    # the integrator integrates the error at sample k with r_k, not r_{k+1}
    z1 = z + plant.dt * (r - x @ plant.C.ravel())
    np.testing.assert_allclose(plans[..., 1], -(x1 @ g.Kx) - g.Ki * z1, rtol=1e-10)


def test_policy_rollouts_are_cut_where_they_leave_the_range():
    plant = load_plant("magnetic_levitation")
    torch.manual_seed(0)
    policy = Policy(net_config(hidden=8, experts=1)).eval()
    rt = PolicyRuntime(policy, _meta(plant))
    amps = [np.array([1.0, 2.0]) * plant.amplitude_scale]
    wide = {plant.name: np.full(plant.order, np.inf)}
    w_all, c_all = aggregate([plant], rt, 0.0, amps, wide, 100, 8, 3)
    bound = 0.5 * np.abs(w_all.state).max(axis=(0, 1))[: plant.order]
    tight = {plant.name: bound}
    w_cut, c_cut = aggregate([plant], rt, 0.0, amps, tight, 100, 8, 3)
    assert 0 < c_cut[plant.name] < c_all[plant.name]
    assert np.all(np.abs(w_cut.state).max(axis=(0, 1))[: plant.order] <= bound + 1e-6)
    assert np.all(np.isfinite(w_all.target))
    ds = WindowTensors(w_cut)
    n = len(ds)
    ds.append(w_all)
    assert len(ds) == n + len(w_all)
    assert torch.equal(ds.tensors["target"][n:], torch.from_numpy(w_all.target))


@pytest.mark.slow
def test_training_with_dagger_grows_the_training_set(tiny_data_dir, tmp_path, mlflow_uri):
    from hydra import compose, initialize_config_dir

    from generalist_control.common.paths import conf_dir
    from helpers import tiny_train_overrides, train

    overrides = tiny_train_overrides(
        tiny_data_dir, tmp_path, mlflow_uri, "logger.log_model=false", "trainer.max_epochs=3",
        "model.hidden=8", "closed_loop.systems=[]", "dagger.start_epoch=1", "dagger.every=1",
        "dagger.rounds=2", "dagger.sampler.rollouts=2", "dagger.sampler.duration=2.0",
    )  # fmt: skip
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics, objects = train(cfg)
    dm = objects["datamodule"]
    (cb,) = [c for c in objects["trainer"].callbacks if type(c).__name__ == "DAggerCallback"]
    assert cb.done == 2
    assert [r["beta"] for r in cb.history] == [0.5, 0.25]  # dagger.beta, decayed by half
    added = sum(r["windows"] for r in cb.history)
    assert added > 0
    assert (
        len(dm.train_set)
        == dm.meta()["n_train"]
        == objects["model"].hparams.meta["n_train"] + added
    )
    assert np.isfinite(metrics["val/loss"])


def test_bumpless_integrator_is_the_tracked_one_on_expert_runs_and_velocity_form_elsewhere():
    plant = load_plant("two_mass_spring")
    g = design_lqi(plant)
    r = np.full((2, 40), 1.5)
    tr = simulate(plant, LQIController(plant), r)
    x = tr.x[:, :40]
    ctrl = LQIController(plant)
    ctrl.reset(2)
    tracked = []
    for k in range(40):
        tracked.append(ctrl.z.copy())
        ctrl.step(x[:, k], r[:, k])
    z = bumpless_integrator(plant, x, tr.u, r)
    np.testing.assert_allclose(z, np.array(tracked).T, rtol=1e-9, atol=1e-12)
    # any applied controls: the label is the LQI law in velocity form
    u = np.random.default_rng(0).normal(size=(2, 40))
    z = bumpless_integrator(plant, x, u, r)
    label = -(x @ g.Kx) - g.Ki * z
    y = x @ plant.C[0]
    velocity = (
        u[:, :-1] - (x[:, 1:] - x[:, :-1]) @ g.Kx - g.Ki * plant.dt * (r[:, :-1] - y[:, :-1])
    )
    np.testing.assert_allclose(label[:, 1:], velocity, rtol=1e-9, atol=1e-9)


def _sampler(plants, **settings):
    sampler_settings = config_section(
        SamplerSettings, "dagger.sampler", **{"families": 0, **settings}
    )
    return RolloutSampler(plants, sampler_settings, RolloutData(20.0, {}, 0.25, 10), 0)


def test_the_sampler_takes_each_plant_s_data_variants_in_turn():
    """variants.data=k: the nominal version and k variants per round, wrapping around."""
    from generalist_control.common.sections import read_section
    from generalist_control.plants.variants import make_variant

    servo, unstable = load_plant("dc_servo"), load_plant("unstable")
    v = [make_variant(servo, {"B[2]": f}) for f in (0.8, 0.9, 1.1)]
    plants = [servo, *v, unstable]  # as dagger_plants orders them: nominal, then variants
    assert _sampler(plants).round_plants(0) == plants

    def taking(k):
        return _sampler(plants, variants=VariantSettings(data=k, fresh=0, seed=3001))

    assert taking(2).round_plants(0) == [servo, v[0], v[1], unstable]
    assert taking(2).round_plants(1) == [servo, v[2], v[0], unstable]
    assert taking(2).round_plants(2) == [servo, v[1], v[2], unstable]
    assert taking(0).round_plants(0) == [servo, unstable]
    assert taking(9).round_plants(0) == plants
    with pytest.raises(ValueError, match="dagger.sampler.variants.data must be a non-negative"):
        node = dataclasses.asdict(config_section(SamplerSettings, "dagger.sampler"))
        node["variants"] = {"data": -1, "fresh": 0, "seed": 1}
        read_section(SamplerSettings, node, "dagger.sampler")


def test_each_plant_version_gets_its_own_rollout_references():
    """Variants share their plant's name, yet each version's rollouts are its own draws."""
    from generalist_control.plants.variants import make_variant

    servo = load_plant("dc_servo")
    plants = [servo, make_variant(servo, {"B[2]": 0.8}), make_variant(servo, {"B[2]": 1.2})]
    specs = _sampler(plants, rollouts=3, duration=2.0).specs(0, plants)
    refs = [spec[0][:, 0] for spec in specs]
    assert len(specs) == 3 and all(len(r) == 3 for r in refs)
    assert not np.allclose(refs[0], refs[1]) and not np.allclose(refs[1], refs[2])
    # the round's draws: amplitudes uniform in +-limit, from seed + round
    want = np.random.default_rng(0).uniform(-20.0, 20.0, 3) * servo.amplitude_scale
    np.testing.assert_array_equal(refs[0], want)
    assert not np.allclose(_sampler(plants, rollouts=3).specs(1, plants)[0][0][:, 0], want)


def _hand_lqi_law(plant):
    """The gains of u = -Kx x - Ki z for ``plant``: python-control's LQR of [x; z], z' = r - y."""
    import control

    n = plant.order
    A = np.block([[plant.A, np.zeros((n, 1))], [-plant.C.reshape(1, n), np.zeros((1, 1))]])
    B = np.vstack([plant.B.reshape(n, 1), [[0.0]]])
    K, _, _ = control.lqr(A, B, plant.Q, plant.R)
    return np.asarray(K)[0, :n], float(np.asarray(K)[0, n])


def test_fresh_variants_are_new_each_round_fit_and_labelled_by_their_own_expert():
    """variants.fresh=k: k new variants per plant and round, each its own LQI's."""
    from generalist_control.plants.variants import parameter_ranges

    servo, unstable = load_plant("dc_servo"), load_plant("unstable")

    def fresh(plants):
        settings = config_section(
            SamplerSettings,
            "dagger.sampler",
            duration=5.0,
            variants=VariantSettings(data=0, fresh=2, seed=3001),
        )
        return RolloutSampler(plants, settings, RolloutData(20.0, {}, 0.2, 10), 0)

    cb = fresh([servo, unstable])
    first = cb.round_plants(0)[2:]
    assert [p.name for p in first] == ["dc_servo"] * 2 + ["unstable"] * 2
    second = cb.round_plants(1)[2:]
    assert len(cb.fresh["dc_servo"]) == 4  # every round's factors are kept
    for name in ("dc_servo", "unstable"):
        factors = [tuple(f.values()) for f in cb.fresh[name]]
        assert len(set(factors)) == 4  # none repeats across rounds
        for f in cb.fresh[name]:
            assert set(f) == set(parameter_ranges(load_plant(name), 0.2))
            assert all(0.8 <= v <= 1.2 for v in f.values())
    again = fresh([servo, unstable]).round_plants(0)[2:]
    assert [p.A.tolist() for p in again] == [p.A.tolist() for p in first]
    assert _sampler([servo]).round_plants(0) == [servo]
    # a fresh variant's windows carry the law of its own LQI, not the nominal plant's
    v = second[0]
    amps = np.array([1.0]) * v.amplitude_scale
    w, _ = aggregate([v], None, 1.0, [amps], {v.name: np.full(v.order, np.inf)}, 60, 8, 3)
    Kx, Ki = _hand_lqi_law(v)
    tr = simulate(v, LQIController(v), np.repeat(amps[:, None], 60, axis=1))
    z = np.cumsum(np.r_[0.0, (tr.r[0] - tr.y[0, :60])[:-1]]) * v.dt  # integral before sample
    law = -(tr.x[0, :60] @ Kx) - Ki * z
    np.testing.assert_allclose(w.target[:, 0], law[:58], rtol=1e-5, atol=1e-7)
    nominal_kx, _ = _hand_lqi_law(servo)
    assert not np.allclose(Kx, nominal_kx, rtol=1e-3)


class _NoisyLQI:
    """Reference for noise injection: plant ``i``'s LQI law plus ``sigma[i] * e_k``.

    ``e_k`` is the k-th draw of ``rows_total`` standard normals from ``default_rng(seed)``,
    of which this plant's rows are ``rows``: the documented generator, drawn over all rows.
    """

    def __init__(self, plant, sigma, draws, rows):
        self.lqi, self.sigma, self.draws, self.rows = LQIController(plant), sigma, draws, rows

    def reset(self, batch_size):
        self.lqi.reset(batch_size)
        self.k = 0

    def step(self, x, r):
        u = self.lqi.step(x, r) + self.sigma * self.draws[self.k][self.rows]
        self.k += 1
        return u


def test_control_noise_moves_the_named_plant_and_the_labels_stay_the_experts_law():
    """``noise``: white noise on one plant's executed control; labels are the clean LQI law."""
    from generalist_control.simulation.simulate import Run, simulate_many

    a, b = load_plant("dc_servo"), load_plant("unstable")
    steps, seed, sigma = 40, 11, 0.3
    refs = np.repeat(np.array([[1.0], [-2.0]]), steps, axis=1)
    gen = np.random.default_rng(seed)
    draws = [gen.standard_normal(4) for _ in range(steps)]
    ctrl = MixedController(None, 1.0, noise={a.name: sigma}, seed=seed)
    u_a, u_b = (t.u for t in simulate_many([Run(a, refs), Run(b, refs)], ctrl))
    want_a = simulate(a, _NoisyLQI(a, sigma, draws, slice(0, 2)), refs)
    np.testing.assert_allclose(u_a, want_a.u, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(u_b, simulate(b, LQIController(b), refs).u, rtol=0, atol=1e-12)
    assert np.abs(u_a - simulate(a, LQIController(a), refs).u).max() > 0.1  # it did move a

    # the round's windows: the visited (noisy) states, labelled by the expert's own law there
    big = {p.name: np.full(p.order, np.inf) for p in (a, b)}
    amps = [np.array([1.0, -2.0])]
    w, _ = aggregate([a], None, 1.0, amps, big, steps, 8, 3, ["integral"],
                     noise={a.name: sigma}, seed=seed)  # fmt: skip
    gen = np.random.default_rng(seed)  # this round holds plant a's two rows alone
    alone = simulate(a, _NoisyLQI(a, sigma, [gen.standard_normal(2) for _ in refs[0]], ...), refs)
    g = design_lqi(a)
    z = np.concatenate([np.zeros((2, 1)), np.cumsum(a.dt * (refs - alone.y[:, :steps]), 1)], 1)
    law = -(alone.x[:, :steps] @ g.Kx) - g.Ki * z[:, :steps]  # the clean law at each state
    np.testing.assert_allclose(w.target[:, 0], law[:, : steps - 2].reshape(-1), rtol=1e-6,
                               atol=1e-6)  # fmt: skip
    executed = alone.u[:, : steps - 2].reshape(-1)
    assert np.abs(w.target[:, 0] - executed).max() > 0.1  # not the noisy control executed
    with pytest.raises(ValueError, match="noise must be finite and >= 0"):
        MixedController(None, 1.0, noise={a.name: -0.1})


def test_sampler_noise_and_actuator_scale_with_each_plant_s_control_scale(monkeypatch):
    """noise and actuator offset are fractions of the policy's control scale per plant."""
    import generalist_control.training.sampler as sampler_module
    from generalist_control.training.settings import ActuatorSettings

    plants = [load_plant("dc_servo"), load_plant("unstable")]
    policy = Policy(net_config(hidden=8, experts=1))
    with torch.no_grad():
        policy.normaliser.control_scale.copy_(
            torch.arange(1.0, 1.0 + len(policy.normaliser.control_scale))
        )
    runtime = PolicyRuntime(policy, _meta(*plants))
    captured = {}

    def spy(plants_, specs, runtime_, beta, noise, seed, actuator):
        captured.update(noise=noise, seed=seed, actuator=actuator, beta=beta)

    monkeypatch.setattr(sampler_module, "run_rollouts", spy)
    settings = config_section(
        SamplerSettings, "dagger.sampler", rollouts=1, duration=1.0, families=0, noise=0.1,
        actuator=ActuatorSettings(lag=0.5, offset=0.2),
    )  # fmt: skip
    RolloutSampler(plants, settings, RolloutData(20.0, {}, 0.25, 10), 5).run(2, runtime, 0.3)
    assert captured["noise"] == pytest.approx({p.name: 0.1 * (1.0 + p.tag) for p in plants})
    for p in plants:
        assert captured["actuator"][p.name] == pytest.approx((0.5, 0.2 * (1.0 + p.tag)))
    assert captured["seed"] == 5 + 7901 * 3 and captured["beta"] == 0.3


def test_worst_first_rolls_out_the_plants_the_policy_controls_worst():
    """A law that is LQI on two plants, half LQI's gains on one, none on an unstable one."""
    names = ["dc_servo", "cstr", "unstable", "mass_spring_damper"]

    def gains(p):
        g = design_lqi(p)
        k = {"unstable": 0.0, "cstr": 0.5}.get(p.name, 1.0)
        return dataclasses.replace(g, Kx=k * g.Kx, Ki=k * g.Ki)

    pol, meta = lqi_law_policy(names, gains)
    plants = [load_plant(n) for n in names]
    runtime = PolicyRuntime(pol, meta)
    assert [p.name for p in WorstFirst(pool=4)(plants, 2, 0, runtime)] == ["unstable", "cstr"]
    assert [p.name for p in WorstFirst(pool=2)(plants, 1, 1, runtime)] == ["unstable"]  # 2, 3
    assert [p.name for p in WorstFirst(pool=2)(plants, 1, 0, runtime)] == ["cstr"]  # 0, 1
    assert InTurn()(plants, 2, 1, None) == plants[2:]  # the default: in turn, nothing scored
    with pytest.raises(ValueError, match="give the round's runtime"):
        WorstFirst(pool=2)(plants, 1, 0, None)
    with pytest.raises(ValueError, match="dagger_pick.pool must be >= 1"):
        WorstFirst(pool=0)
