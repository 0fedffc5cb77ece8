"""DAgger: expert labels on visited states, checked against the expert's own trajectories."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from generalist_control.data.windows import build_windows
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.plant import pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import simulate
from generalist_control.training.dagger import aggregate, bumpless_integrator, expert_plans
from generalist_control.training.datamodule import WindowTensors


@pytest.mark.parametrize("name", ["magnetic_levitation", "two_tank", "two_mass_spring"])
def test_pure_expert_round_reproduces_the_demonstration_windows(name):
    """With beta = 1 the expert's plan at each visited state is what it then did."""
    plant = load_plant(name)
    amps = np.array([1.0, -2.5]) * plant.amplitude_scale
    steps, big = 60, np.full(plant.order, np.inf)
    windows, counts = aggregate([plant], None, 1.0, {name: amps}, {name: big}, steps, 8, 3)
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
    """With model.integral the label is the LQI law at the window's own [x; z]."""
    plant = load_plant("cstr")
    g = design_lqi(plant)
    torch.manual_seed(0)
    policy = Policy({"hidden": 8, "experts": 1, "integral": 1}).eval()
    meta = {"tags": {plant.name: plant.tag}, "orders": {plant.name: plant.order},
            "dt": plant.dt, "history": 8, "horizon": 3}  # fmt: skip
    runtime = PolicyRuntime(policy, meta)
    big = {plant.name: np.full(plant.order, np.inf)}
    amps = {plant.name: np.array([1.0, -2.0])}
    with pytest.raises(ValueError, match="takeover=tracked"):
        aggregate([plant], runtime, 0.5, amps, big, 40, 8, 3, "bumpless", integral=True)
    w, _ = aggregate([plant], runtime, 0.5, amps, big, 40, 8, 3, "tracked", integral=True)
    assert w.state.shape[1:] == (8, 5)
    newest = w.state[:, -1].astype(float)
    law = -(newest[:, : plant.order] @ g.Kx) - g.Ki * newest[:, 4]
    np.testing.assert_allclose(w.target[:, 0], law, rtol=1e-4, atol=1e-5)
    assert np.abs(newest[:, 4]).max() > 0.1  # the policy's rollouts moved the integrator


def test_rounds_for_a_control_history_policy_carry_the_executed_controls():
    """With model.control_history the last channel is the mixed control executed before.

    The rollout's policy saw those same windows: the executed control is ``0.5 u_expert +
    0.5 u_policy``, and ``u_policy`` recomputed by the network from the aggregated windows
    (previous control included) is the one the rollout blended.
    """
    from generalist_control.deploy.export import backend
    from generalist_control.simulation.simulate import Run, simulate_many
    from generalist_control.training.dagger import MixedController

    plant = load_plant("hydraulic_actuator")
    torch.manual_seed(0)
    on = {"control_history": 1, "linear_skip": 1, "history_context": 1}
    policy = Policy({"hidden": 8, "experts": 1, "integral": 1, **on}).eval()
    with torch.no_grad():  # the skip path's gains start at zero: give them weight, so that
        policy.net.skip.weight.normal_(0.0, 0.3)  # the previous control reaches the output
    meta = {"tags": {plant.name: plant.tag}, "orders": {plant.name: plant.order},
            "dt": plant.dt, "history": 8, "horizon": 3}  # fmt: skip
    big = {plant.name: np.full(plant.order, np.inf)}
    amps = np.array([1.0, -2.0])
    args = ([plant], PolicyRuntime(policy, meta), 0.5, {plant.name: amps}, big, 40, 8, 3)
    w, _ = aggregate(*args, "tracked", integral=True, controls=True)
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


def test_per_plant_expert_share_blends_each_plant_with_its_own_beta():
    """``betas`` gives one plant its own share: 1 there is the expert, 0.5 elsewhere a blend."""
    from generalist_control.simulation.simulate import Run, simulate_many
    from generalist_control.training.dagger import MixedController

    a, b = load_plant("dc_servo"), load_plant("unstable")
    torch.manual_seed(0)
    policy = Policy({"hidden": 8, "experts": 1}).eval()
    meta = {"tags": {p.name: p.tag for p in (a, b)}, "orders": {p.name: p.order for p in (a, b)},
            "dt": a.dt, "history": 8, "horizon": 3}  # fmt: skip
    refs = np.repeat(np.array([[1.0], [-2.0]]), 30, axis=1)
    runs = [Run(a, refs), Run(b, refs)]

    def executed(beta, betas=None):
        ctrl = MixedController(PolicyRuntime(policy, meta), beta, betas)
        return [t.u for t in simulate_many(runs, ctrl)]

    u_a, u_b = executed(0.5, {a.name: 1.0})
    expert_a = simulate(a, LQIController(a), refs).u
    np.testing.assert_allclose(u_a, expert_a, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(u_b, executed(0.5)[1], rtol=1e-12, atol=1e-12)
    assert np.abs(u_a - executed(0.5)[0]).max() > 1e-3  # the override changed plant a only
    with pytest.raises(ValueError, match="beta must be 1"):
        MixedController(None, 1.0, {a.name: 0.5})


def _focus_callback(**kw):
    from generalist_control.training.dagger_callback import DAggerCallback

    plants = [load_plant("dc_servo"), load_plant("unstable")]
    return DAggerCallback(plants, rollouts=4, families=None, **kw)


def test_focus_adds_rollouts_and_expert_share_to_the_plants_still_lost():
    """A plant scored s gets round(focus s rollouts) more steps; the off switch changes nothing."""
    from types import SimpleNamespace

    metrics = {"val/closed_loop/unstable": torch.tensor(0.75),
               "val/closed_loop/dc_servo": torch.tensor(float("nan"))}  # fmt: skip
    trainer = SimpleNamespace(callback_metrics=metrics)
    off, on = _focus_callback(), _focus_callback(focus=2.0, focus_beta=0.5)
    assert off._lost(trainer) == {}
    lost = on._lost(trainer)
    assert lost == {"unstable": 0.75}  # a NaN score counts as no score
    base, focused = off._rollouts(50, off.plants), on._rollouts(50, on.plants, lost)
    servo, unstable = 0, 1  # specs come in the plants' order
    assert len(base[unstable][0]) == 4 and len(focused[unstable][0]) == 4 + 6
    assert len(focused[servo][0]) == 4
    np.testing.assert_array_equal(base[servo][0], focused[servo][0])  # drawn first
    np.testing.assert_array_equal(base[unstable][0], off._rollouts(50, off.plants, lost)[1][0])
    metrics["val/closed_loop/unstable"] = torch.tensor(3.0)  # clipped to 1
    assert on._lost(trainer) == {"unstable": 1.0}
    for bad in ({"focus": -1.0}, {"focus_beta": 1.5}):
        with pytest.raises(ValueError, match="dagger.focus"):
            _focus_callback(**bad)


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
    policy = Policy({"hidden": 8, "experts": 1}).eval()
    meta = {"tags": {plant.name: plant.tag}, "orders": {plant.name: plant.order},
            "dt": plant.dt, "history": 8, "horizon": 3}  # fmt: skip
    rt = PolicyRuntime(policy, meta)
    amps = {plant.name: np.array([1.0, 2.0]) * plant.amplitude_scale}
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
    from generalist_control.training.fit import train
    from helpers import tiny_train_overrides

    overrides = tiny_train_overrides(
        tiny_data_dir, tmp_path, mlflow_uri, "logger.log_model=false", "trainer.max_epochs=3",
        "model.hidden=8", "closed_loop.systems=[]", "dagger.start_epoch=1", "dagger.every=1",
        "dagger.rounds=2", "dagger.rollouts=2", "dagger.duration=2.0",
    )  # fmt: skip
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    metrics, objects = train(cfg)
    dm = objects["datamodule"]
    (cb,) = [c for c in objects["trainer"].callbacks if type(c).__name__ == "DAggerCallback"]
    assert cb.done == 2
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


def test_dagger_variants_takes_each_plants_variants_in_turn():
    """dagger.variants=k: the nominal version and k variants per round, wrapping around."""
    from generalist_control.plants.variants import make_variant
    from generalist_control.training.dagger_callback import DAggerCallback

    servo, unstable = load_plant("dc_servo"), load_plant("unstable")
    v = [make_variant(servo, {"B[2]": f}) for f in (0.8, 0.9, 1.1)]
    plants = [servo, *v, unstable]  # as dagger_plants orders them: nominal, then variants
    assert DAggerCallback(plants, families=None)._round_plants() == plants
    cb = DAggerCallback(plants, families=None, variants=2)
    assert cb._round_plants() == [servo, v[0], v[1], unstable]
    cb.done = 1
    assert cb._round_plants() == [servo, v[2], v[0], unstable]
    cb.done = 2
    assert cb._round_plants() == [servo, v[1], v[2], unstable]
    assert DAggerCallback(plants, families=None, variants=0)._round_plants() == [servo, unstable]
    assert DAggerCallback(plants, families=None, variants=9)._round_plants() == plants
    with pytest.raises(ValueError, match="dagger.variants must be a non-negative integer"):
        DAggerCallback(plants, families=None, variants=-1)


def test_each_plant_version_gets_its_own_rollout_references():
    """Variants share their plant's name, yet each version's rollouts are its own draws."""
    from generalist_control.plants.variants import make_variant
    from generalist_control.training.dagger_callback import DAggerCallback

    servo = load_plant("dc_servo")
    plants = [servo, make_variant(servo, {"B[2]": 0.8}), make_variant(servo, {"B[2]": 1.2})]
    specs = DAggerCallback(plants, rollouts=3, families=None)._rollouts(40, plants)
    refs = [spec[0][:, 0] for spec in specs]
    assert len(specs) == 3 and all(len(r) == 3 for r in refs)
    assert not np.allclose(refs[0], refs[1]) and not np.allclose(refs[1], refs[2])
    with pytest.raises(ValueError, match="2 rollout specs for 3 plants"):
        aggregate(plants, None, 1.0, specs[:2], {servo.name: np.ones(3)}, 40, 8, 3)


def _hand_lqi_law(plant):
    """The gains of u = -Kx x - Ki z for ``plant``: python-control's LQR of [x; z], z' = r - y."""
    import control

    n = plant.order
    A = np.block([[plant.A, np.zeros((n, 1))], [-plant.C.reshape(1, n), np.zeros((1, 1))]])
    B = np.vstack([plant.B.reshape(n, 1), [[0.0]]])
    K, _, _ = control.lqr(A, B, plant.Q, plant.R)
    return np.asarray(K)[0, :n], float(np.asarray(K)[0, n])


def test_fresh_variants_are_new_each_round_fit_and_labelled_by_their_own_expert():
    """dagger.fresh_variants=k: k new variants per plant and round, each its own LQI's."""
    from generalist_control.plants.variants import parameter_ranges
    from generalist_control.training.dagger_callback import DAggerCallback

    servo, unstable = load_plant("dc_servo"), load_plant("unstable")
    cb = DAggerCallback([servo, unstable], families=None, fresh_variants=2, variant_range=0.2)
    first = cb._fresh_plants(100)
    assert [p.name for p in first] == ["dc_servo"] * 2 + ["unstable"] * 2
    cb.done = 1
    second = cb._fresh_plants(100)
    assert len(cb.fresh["dc_servo"]) == 4  # every round's factors are kept
    for name in ("dc_servo", "unstable"):
        factors = [tuple(f.values()) for f in cb.fresh[name]]
        assert len(set(factors)) == 4  # none repeats across rounds
        for f in cb.fresh[name]:
            assert set(f) == set(parameter_ranges(load_plant(name), 0.2))
            assert all(0.8 <= v <= 1.2 for v in f.values())
    again = DAggerCallback([servo, unstable], families=None, fresh_variants=2, variant_range=0.2)
    assert [p.A.tolist() for p in again._fresh_plants(100)] == [p.A.tolist() for p in first]
    assert DAggerCallback([servo], families=None)._fresh_plants(100) == []
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
    with pytest.raises(ValueError, match="dagger.fresh_variants must be a non-negative"):
        DAggerCallback([servo], families=None, fresh_variants=-1)


def test_fresh_pool_rolls_out_on_the_variants_where_the_loop_is_worst():
    """dagger.fresh_pool: of each plant's pool, the fresh_variants worst under the controller.

    The screened controller is the nominal plant's LQI law on each variant (what a user
    without redesign has); its error against each variant's own LQI, computed by hand from
    two simulations, must rank the chosen variants first.
    """
    from generalist_control.simulation.simulate import PerPlantController
    from generalist_control.simulation.variants import sample_variants
    from generalist_control.training.dagger_callback import SCREEN_AMPLITUDES, DAggerCallback

    plants = [load_plant("mass_spring_damper"), load_plant("dc_servo")]
    gains = {p.name: design_lqi(p) for p in plants}
    nominal_law = PerPlantController(lambda p: LQIController(p, gains[p.name]))
    cb = DAggerCallback(plants, families=None, fresh_variants=2, fresh_pool=6)
    chosen = cb._fresh_plants(200, nominal_law)
    assert [p.name for p in chosen] == ["mass_spring_damper"] * 2 + ["dc_servo"] * 2
    for k, p in enumerate(plants):
        pool = sample_variants(p, 6, cb.variant_seed, cb.variant_range, (20.0, -20.0), 200)
        err = []
        for v in pool.kept:
            refs = np.repeat(np.asarray(SCREEN_AMPLITUDES)[:, None] * p.amplitude_scale, 200, 1)
            own = simulate(v.plant, LQIController(v.plant), refs)
            nom = simulate(v.plant, LQIController(v.plant, gains[p.name]), refs)
            rel = np.mean((nom.y - own.y) ** 2, axis=1) / np.mean(own.y**2, axis=1)
            err.append(min(1.0, rel.mean()))
        worst = sorted(np.argsort(err)[::-1][:2])
        want = [pool.kept[j].plant.A.tolist() for j in worst]
        assert [q.A.tolist() for q in chosen[2 * k : 2 * k + 2]] == want
        np.testing.assert_allclose(cb.screened[p.name], [err[j] for j in worst], rtol=1e-9)
        assert min(cb.screened[p.name]) >= np.median(err)  # the worst, not the draw's first
        # fresh_worst=1 of 3: the draw's first two as they come, the worst of the other four
        # (for dc_servo not the first of them: 8e-6 against 4e-6)
        mixed = DAggerCallback([p], families=None, fresh_variants=3, fresh_pool=6, fresh_worst=1)
        got = mixed._fresh_plants(200, nominal_law)
        rest = 2 + int(np.argmax(err[2:]))
        want = [pool.kept[j].plant.A.tolist() for j in (0, 1, rest)]
        assert [q.A.tolist() for q in got] == want
        assert mixed.screened[p.name] == pytest.approx([err[rest]], rel=1e-9)
    with pytest.raises(ValueError, match="dagger.fresh_worst = 3 exceeds"):
        DAggerCallback(plants, families=None, fresh_variants=2, fresh_pool=6, fresh_worst=3)
    with pytest.raises(ValueError, match="screening the pool needs the policy's loop"):
        DAggerCallback(plants, families=None, fresh_variants=1, fresh_pool=3)._fresh_plants(50)
    with pytest.raises(ValueError, match="dagger.fresh_pool = 1 is smaller than"):
        DAggerCallback(plants, families=None, fresh_variants=2, fresh_pool=1)


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
    from generalist_control.training.dagger import MixedController

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
    amps = {a.name: np.array([1.0, -2.0])}
    w, _ = aggregate([a], None, 1.0, amps, big, steps, 8, 3, "tracked",
                     noise={a.name: sigma}, noise_seed=seed)  # fmt: skip
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


def test_dagger_noise_is_a_fraction_of_each_plants_control_scale():
    cb = _focus_callback(noise=0.1)
    policy = Policy({"hidden": 8, "experts": 1})
    with torch.no_grad():
        policy.normaliser.control_scale.copy_(
            torch.arange(1.0, 1.0 + len(policy.normaliser.control_scale))
        )
    want = {p.name: 0.1 * (1.0 + p.tag) for p in cb.plants}
    assert cb._noise(policy, cb.plants) == pytest.approx(want)
    assert _focus_callback()._noise(policy, cb.plants) is None  # 0: off
    with pytest.raises(ValueError, match="dagger.noise must be a finite fraction >= 0"):
        _focus_callback(noise=-0.5)
