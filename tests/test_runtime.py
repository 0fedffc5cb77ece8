"""The policy runtime: stepping equals the batch forward, exports, bad input, safe loading."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch

from generalist_control.data.windows import build_windows, integral_of_error
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.policy_source import resolve
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy, PolicyFileError, load_policy, save_policy
from generalist_control.plants.catalog import load_plant
from generalist_control.plants.definition import MAX_ORDER, pad_states
from generalist_control.simulation.lqi import LQIController, design_lqi
from generalist_control.simulation.simulate import Run, simulate, simulate_many
from helpers import lqi_law_policy, net_config

PLANTS = ("cstr", "hydraulic_actuator")  # orders 2 and 3


def _meta(history: int = 8) -> dict:
    return {
        "tags": {p: load_plant(p).tag for p in PLANTS},
        "orders": {p: load_plant(p).order for p in PLANTS},
        "dt": 0.05,
        "history": history,
        "horizon": 3,
    }


@pytest.fixture(
    scope="module",
    params=[0, 1, 2, 3, 4],
    ids=["paper", "ours-no-integral", "ours", "tag-free-controls", "tag-free-transitions"],
)
def policy(request) -> Policy:
    """A random policy with non-trivial normaliser scales (no training needed here).

    ``ours-no-integral``: window scaling and a whole-window linear skip on, its weights made
    non-zero; ``ours``: the same and the tracking-error integral as a state
    channel; ``tag-free-controls``: that, without the tag and with the previous control as
    a channel, the plant inferred from the window (an inferred plant and a context skip);
    ``tag-free-transitions``: that with a 12-sample window read by the transition
    identifier and each plant's one-step model with its fitted input gain, the law reading
    the newest 8.
    """
    torch.manual_seed(0)
    integral = request.param > 1
    cfg = {"hidden": 16, "experts": 3, "window_scale": request.param > 0}
    cfg["channels"] = ["integral"] if integral else []
    if request.param in (1, 2):
        cfg |= {"skip": "linear", "skip_samples": 8}
    if request.param >= 3:
        cfg |= {"channels": ["integral", "previous_control"], "skip": "context"}
        cfg |= {"plant": "inferred", "models": None}
    if request.param == 4:
        cfg |= {"history": 12, "law_history": 8, "models": {"input_gain": [0.75, 1.25]}}
    pol = Policy(net_config(**cfg)).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        identifier = getattr(pol.net.plant, "identifier", None)
        models = getattr(identifier, "models", None)
        if models is not None:  # each plant's one-step model: non-zero, so evidence differs
            models.params.weight.normal_(0.0, 0.1, generator=g)
        if pol.net.skip is not None:  # the skip's own control fed back: small, or it runs away
            pol.net.skip.gains.weight.normal_(0.0, 0.02, generator=g)
    pol.normaliser.state_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.ref_scale.uniform_(0.5, 3.0, generator=g)
    pol.normaliser.control_scale.uniform_(0.5, 3.0, generator=g)
    if request.param >= 3:  # the random net's feedback on its own control: kept bounded
        pol.normaliser.state_scale[:, -1] = 10.0
    return pol


def _lqi_trajectory(name: str, amplitude: float, steps: int = 60):
    plant = load_plant(name)
    r = np.full((1, steps), amplitude)
    tr = simulate(plant, LQIController(plant), r)
    return plant, tr


def test_stepping_equals_the_batch_forward_on_built_windows(policy):
    """Each step's plan equals the network on the window the one window builder makes."""
    runtime = PolicyRuntime(policy, _meta(policy.history))
    for name, amp in (("cstr", 1.5), ("hydraulic_actuator", -3.0)):
        plant, tr = _lqi_trajectory(name, amp)
        runtime.reset(name)
        plans = []
        for k in range(tr.r.shape[1]):
            u = runtime.step(tr.x[0, k], tr.r[0, k])
            assert u == pytest.approx(float(runtime.plan[0, 0]))
            plans.append(runtime.plan[0])
        plans = np.array(plans)
        x = pad_states(tr.x[:, :-1])
        z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt) if runtime.integral else None
        tag, order = np.array([plant.tag]), np.array([plant.order])
        # the previous-control channel holds what the runtime itself issued
        issued = plans[None, :, 0].astype(np.float64)
        w = build_windows(x, tr.r, issued, tag, order, runtime.history, 1, z, runtime.controls)
        expected, _ = policy.predict_windows(w)
        # float32 sums in another order: ~1e-6 of a control (the plants' evidence is a log)
        np.testing.assert_allclose(plans, expected, rtol=1e-5, atol=2e-6)
        if runtime.integral:  # the runtime's integrator is the expert's, sample by sample
            np.testing.assert_allclose(
                runtime.z, z[:, -1] + plant.dt * (tr.r - tr.y[:, :-1])[:, -1]
            )


def test_batched_stepping_equals_single_runs(policy):
    runtime = PolicyRuntime(policy, _meta(policy.history))
    runs = [_lqi_trajectory("cstr", 2.0), _lqi_trajectory("hydraulic_actuator", 0.5)]
    singles = []
    for plant, tr in runs:
        runtime.reset(plant.name)
        singles.append([runtime.step(tr.x[0, k], tr.r[0, k]) for k in range(20)])
    runtime.reset([p.name for p, _ in runs])
    batched = []
    for k in range(20):
        x = np.stack([pad_states(tr.x[:, k : k + 1])[0, 0] for _, tr in runs])
        r = np.array([tr.r[0, k] for _, tr in runs])
        batched.append(runtime.step(x, r))
    # float32 sums over a batch differ from single rows in the last bits (~1e-7 of a control)
    np.testing.assert_allclose(np.array(batched).T, np.array(singles), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("backend", ["onnx"])
def test_exports_equal_pytorch_within_1e_5(policy, backend):
    rng = np.random.default_rng(0)
    reference = PolicyRuntime(policy, _meta(policy.history), backend="torch")
    exported = PolicyRuntime(policy, _meta(policy.history), backend=backend)
    names = ["cstr", "hydraulic_actuator", "cstr", "hydraulic_actuator", "cstr"]
    for rt in (reference, exported):
        rt.reset(names)
    for _ in range(12):  # batch 5 (the exports were traced at batch 2: dynamic batch axis)
        x = rng.normal(scale=2.0, size=(5, MAX_ORDER))
        r = rng.normal(scale=5.0, size=5)
        a, b = reference.step(x, r), exported.step(x, r)
        np.testing.assert_allclose(b, a, atol=1e-5, rtol=1e-5)
        np.testing.assert_allclose(exported.plan, reference.plan, atol=1e-5, rtol=1e-5)


def test_bad_input_gets_clear_errors(policy):
    runtime = PolicyRuntime(policy, _meta(policy.history))
    with pytest.raises(RuntimeError, match="reset"):
        runtime.step([0.0, 0.0], 1.0)
    with pytest.raises(KeyError, match="unknown plant 'pendulum'.*cstr, hydraulic_actuator"):
        runtime.reset("pendulum")
    runtime.reset("hydraulic_actuator")
    with pytest.raises(ValueError, match=r"shape \(2,\); plant 'hydraulic_actuator' has 3"):
        runtime.step([0.0, 0.0], 1.0)
    with pytest.raises(ValueError, match="NaN or inf"):
        runtime.step([0.0, np.nan, 0.0], 1.0)
    with pytest.raises(ValueError, match="NaN or inf"):
        runtime.step([0.0, 0.0, 0.0], np.inf)
    runtime.reset(["cstr", "cstr"])
    with pytest.raises(ValueError, match="expected \\(2, 4\\)"):
        runtime.step(np.zeros((3, 4)), np.zeros(3))
    with pytest.raises(ValueError, match="unknown backend 'tensorrt'"):
        PolicyRuntime(policy, _meta(policy.history), backend="tensorrt")
    with pytest.raises(FileNotFoundError, match="python train.py"):
        resolve("no/such/policy.ckpt")


class _Evil:
    def __reduce__(self):
        return (print, ("arbitrary code ran",))


def test_loading_is_weights_only(policy, tmp_path):
    path = save_policy(tmp_path / "policy.ckpt", policy, _meta(policy.history))
    loaded = PolicyRuntime.load(path)
    loaded.reset("cstr")
    ref = PolicyRuntime(policy, _meta(policy.history))
    ref.reset("cstr")
    assert loaded.step([0.3, -0.1], 1.0) == pytest.approx(ref.step([0.3, -0.1], 1.0), abs=1e-7)
    evil = tmp_path / "evil.ckpt"
    blob = torch.load(path, weights_only=True)
    blob["meta"]["payload"] = _Evil()
    with evil.open("wb") as fh:
        torch.save(blob, fh, pickle_module=pickle)
    with pytest.raises(PolicyFileError, match="is not a policy file of this project"):
        load_policy(evil)


def _lqi_law_policy(names) -> tuple[Policy, dict]:
    """A real integrating policy whose skip path *is* the LQI law.

    Through window scaling (the head is linear) and the runtime's own integrator, it must
    reproduce LQI exactly (:func:`helpers.lqi_law_policy`).
    """
    return lqi_law_policy(names, design_lqi)


def test_an_integrating_policy_built_as_the_lqi_law_reproduces_lqi_in_closed_loop():
    """The runtime's integrator, window builder and normaliser against LQI itself.

    Includes a nonlinear plant (AUV yaw), whose output map goes through the plant.
    """
    names = ("cstr", "hydraulic_actuator", "auv_yaw")
    pol, meta = _lqi_law_policy(names)
    runtime = PolicyRuntime(pol, meta)
    plants = [load_plant(n) for n in names]
    runs = [
        Run(p, np.full((2, 120), a * p.amplitude_scale))
        for p, a in zip(plants, (1, -3, 2), strict=True)
    ]
    gc = simulate_many(runs, RuntimeAdapter(runtime))
    for p, run, tr in zip(plants, runs, gc, strict=True):
        ref = simulate(p, LQIController(p), run.r)
        scale = np.abs(ref.u).max()
        np.testing.assert_allclose(tr.u, ref.u, rtol=0, atol=2e-5 * scale)
        np.testing.assert_allclose(tr.y, ref.y, rtol=0, atol=2e-5 * np.abs(ref.y).max())
    # single-plant stepping with y = C x from the stored output rows gives the same controls
    p, run = plants[0], runs[0]
    ref = simulate(p, LQIController(p), run.r[:1])
    runtime.reset(p.name)
    u = [runtime.step(ref.x[0, k], ref.r[0, k]) for k in range(run.r.shape[1])]
    np.testing.assert_allclose(u, ref.u[0], rtol=0, atol=2e-5 * np.abs(ref.u).max())


def test_an_integrating_policy_needs_an_output_it_can_integrate():
    pol, meta = _lqi_law_policy(("cstr",))
    meta = {**meta, "tags": {"mystery": 0}, "orders": {"mystery": 2}, "outputs": {}}
    runtime = PolicyRuntime(pol, meta)
    runtime.reset("mystery")  # not in the catalogue: no output row to fall back on
    with pytest.raises(ValueError, match=r"no output map for mystery: pass .*step\(x, r, y\)"):
        runtime.step([0.1, 0.2], 1.0)
    assert runtime.z == pytest.approx([0.0])  # nothing advanced on the failed step
    runtime.step([0.1, 0.2], 1.0, y=0.3)
    assert runtime.z == pytest.approx([0.05 * (1.0 - 0.3)])
    with pytest.raises(ValueError, match="output contains NaN"):
        runtime.step([0.1, 0.2], 1.0, y=np.nan)
    with pytest.raises(ValueError, match=r"output has shape \(2,\); expected \(1,\)"):
        runtime.step([0.1, 0.2], 1.0, y=[0.1, 0.2])


@pytest.mark.parametrize(
    ("name", "limits"),
    [("two_mass_spring", {"u_limit": 0.25}), ("cstr", {"rate_limit": 0.5})],
)
def test_runtime_anti_windup_is_lqi_anti_windup_for_the_lqi_law(name, limits):
    """Told the actuator limits, the runtime integrates as AntiWindupLQIController does."""
    from generalist_control.simulation.lqi import AntiWindupLQIController
    from generalist_control.simulation.perturbation import Perturbation
    from generalist_control.simulation.simulate import PerPlantController

    pol, meta = _lqi_law_policy((name,))
    pert = Perturbation(**limits)
    plant = load_plant(name)
    run = Run(plant, np.full((1, 400), 1.0), None, pert)
    aw = simulate_many([run], PerPlantController(lambda p: AntiWindupLQIController(p, pert)))[0]
    plain = simulate_many([run], PerPlantController(LQIController))[0]
    runtime = PolicyRuntime(pol, meta)
    gc_aw = simulate_many([run], RuntimeAdapter(runtime, pert))[0]
    gc = simulate_many([run], RuntimeAdapter(runtime))[0]  # limits cleared again
    scale = np.abs(aw.y).max()
    np.testing.assert_allclose(gc_aw.y, aw.y, rtol=0, atol=1e-4 * scale)
    np.testing.assert_allclose(gc.y, plain.y, rtol=0, atol=1e-4 * np.abs(plain.y).max())
    assert np.abs(plain.y - aw.y).max() > 0.1 * scale  # the limits matter in this scenario


def test_the_previous_control_channel_holds_the_actuated_control():
    """Without limits the window's newest control entry is the last command; with limits,
    what the actuator applied (``Perturbation.actuate``); zero on the first step."""
    torch.manual_seed(3)
    config = net_config(hidden=16, channels=["integral", "previous_control"], skip="context",
                        plant="inferred", models=None)  # fmt: skip
    pol = Policy(config).eval()
    with torch.no_grad():
        pol.net.experts[0][-1].bias.fill_(5.0)  # commands well beyond the limit below
    runtime = PolicyRuntime(pol, _meta())
    assert runtime.controls
    for limit in (None, 0.1):
        runtime.set_actuator_limits(u_limit=limit)
        runtime.reset("cstr")
        commands, seen = [], []
        for k in range(4):
            commands.append(runtime.step([0.01 * k, 0.0], 0.5))
            state, mask, _, _ = runtime.window()
            assert state.shape[-1] == MAX_ORDER + 2 and mask[0, -1, -1] == 1.0
            seen.append(float(state[0, -1, -1]))
        applied = np.array(commands[:-1])
        if limit is not None:
            applied = np.clip(applied, -limit, limit)
            assert np.abs(np.array(commands)).min() > limit  # the limit did act
        np.testing.assert_allclose(seen, [0.0, *applied], rtol=1e-6)
