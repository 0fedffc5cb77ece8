"""The rest-stability training term: against python-control's loops and finite differences."""

from __future__ import annotations

import dataclasses

import control as ct
import numpy as np
import pytest
import torch

from generalist_control.model.rest_loop import (
    equilibrium,
    integral_at_rest,
    loop_parts,
    rest_window,
)
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import design_lqi
from generalist_control.training.rest import RestPenalty, _excess
from generalist_control.training.setup import rest_penalty
from helpers import compose_cfg, lqi_law_policy

PLANTS = ("cstr", "hydraulic_actuator", "two_tank")  # orders 2, 3 and a nonlinear plant


def _gains(k: float):
    def gains(plant):
        g = design_lqi(plant)
        return dataclasses.replace(g, Kx=k * np.asarray(g.Kx), Ki=k * g.Ki)

    return gains


def _eigs(name: str, k: float) -> np.ndarray:
    """Eigenvalues of the hand-built sampled LQI loop on [x; z] (python-control ZOH), gains x k."""
    p = load_plant(name)
    d = ct.c2d(ct.ss(p.A, p.B, p.C, 0), p.dt, "zoh")
    Ad, Bd, C = np.asarray(d.A), np.asarray(d.B), np.asarray(d.C)
    g = design_lqi(p)
    n = Ad.shape[0]
    A = np.zeros((n + 1, n + 1))
    A[:n, :n] = Ad - k * Bd @ np.asarray(g.Kx).reshape(1, n)
    A[:n, n] = -k * Bd.ravel() * g.Ki
    A[n, :n], A[n, n] = -p.dt * C.ravel(), 1.0
    return np.linalg.eigvals(A)


def _penalty(k: float, names=PLANTS, **kw) -> tuple[RestPenalty, torch.nn.Module]:
    pol, meta = lqi_law_policy(names, _gains(k))
    plants = [load_plant(n) for n in names]
    kw.setdefault("per_step", len(names))
    return RestPenalty(plants, meta["tags"], pol.config["history"], False, **kw), pol


def test_the_lqi_law_costs_nothing_and_its_radius_is_lqis():
    pen, pol = _penalty(1.0)
    for _ in range(3):  # references drawn at random: a linear law's loop is the same at any
        term = pen(pol)
        assert term is not None and float(term.detach()) == 0.0
        expected = max(np.abs(_eigs(n, 1.0)).max() for n in PLANTS)
        assert pen.last_radius == pytest.approx(expected, abs=1e-5)


def test_unstable_gains_cost_their_eigenvalues_excess_over_the_target():
    """Gains x 12: each eigenvalue above 1 - slack (1 - rho_LQI) adds its excess; the mean."""
    slack = 0.5
    pen, pol = _penalty(12.0, slack=slack)
    expected = []
    for n in PLANTS:
        target = 1.0 - slack * (1.0 - np.abs(_eigs(n, 1.0)).max())
        mods = np.abs(_eigs(n, 12.0))
        expected.append(np.clip(mods - target, 0.0, None).sum())
    assert max(expected) > 0.3  # the case is a real one: some loop is unstable
    term = pen(pol)
    assert term is not None
    assert float(term.detach()) == pytest.approx(np.mean(expected), abs=1e-4)
    assert pen.last_radius == pytest.approx(max(np.abs(_eigs(n, 12.0)).max() for n in PLANTS))


def test_the_terms_gradient_is_the_eigenvalues_derivative():
    """Against central finite differences, on a loop with the window's defective delay chain."""
    p = load_plant("hydraulic_actuator")
    from generalist_control.simulation.simulate import discretise

    Ad, Bd = discretise(p.A, p.B, p.dt)
    A0, b = (torch.as_tensor(a) for a in loop_parts(Ad, Bd, p.C, p.dt, 4, True, True))
    g = torch.Generator().manual_seed(0)
    law = (torch.randn(len(b), generator=g, dtype=torch.float64) * 0.3).requires_grad_(True)
    target = 0.6
    value, _ = _excess(A0 + torch.outer(b, law), target)
    assert float(value.detach()) > 0
    (grad,) = torch.autograd.grad(value, law)
    d = torch.randn(len(b), generator=g, dtype=torch.float64)

    def f(x: torch.Tensor) -> float:
        mods = np.abs(np.linalg.eigvals((A0 + torch.outer(b, x)).numpy()))
        return float(np.clip(mods - target, 0.0, None).sum())

    eps = 1e-6
    fd = (f(law.detach() + eps * d) - f(law.detach() - eps * d)) / (2 * eps)
    assert float(grad @ d) == pytest.approx(fd, rel=1e-4, abs=1e-7)


def test_a_step_down_the_term_lowers_it():
    pen, pol = _penalty(12.0, names=("cstr", "hydraulic_actuator"))
    pol.train()
    before = pen(pol)
    assert before is not None and float(before.detach()) > 0
    before.backward()
    with torch.no_grad():
        for q in pol.parameters():
            if q.grad is not None:
                q -= 1e-3 * q.grad
    after = pen(pol)
    assert after is not None and float(after.detach()) < float(before.detach())


def test_the_integral_at_rest_is_lqis_for_the_lqi_law():
    pol, meta = lqi_law_policy(("cstr",), design_lqi)
    p = load_plant("cstr")
    x, u, r = equilibrium(p, 2.0)
    g = design_lqi(p)
    z_lqi = -(u + float(np.dot(g.Kx, x))) / float(g.Ki)
    w = rest_window(p, x, 0.0, u, r, history=pol.config["history"], controls=False,
                    tag=meta["tags"]["cstr"])  # fmt: skip
    w = (*(t.float() for t in w[:3]), w[3])
    z = integral_at_rest(pol, w, torch.tensor([u], dtype=torch.float64),
                         torch.tensor([z_lqi + 0.3], dtype=torch.float64),
                         torch.tensor([1.0], dtype=torch.float64))  # fmt: skip
    assert float(z[0]) == pytest.approx(z_lqi, rel=1e-4, abs=1e-5)
    none = integral_at_rest(pol, w, torch.tensor([u + 1e6], dtype=torch.float64),
                            torch.tensor([z_lqi], dtype=torch.float64),
                            torch.tensor([1.0], dtype=torch.float64))  # fmt: skip
    assert torch.isnan(none).all()  # no integral within reach holds that control


def test_the_config_block_is_checked():
    meta = {"tags": {"cstr": load_plant("cstr").tag}}
    plants = [load_plant("cstr")]
    assert rest_penalty(compose_cfg(), plants, meta) is None  # the default recipe: off
    on = compose_cfg("rest.weight=0.5", "model.integral=true")
    pen = rest_penalty(on, plants, meta)
    assert isinstance(pen, RestPenalty) and pen.weight == 0.5
    with pytest.raises(ValueError, match="needs model.integral=true"):
        rest_penalty(compose_cfg("rest.weight=1", "model.integral=false"), plants, meta)
    with pytest.raises(ValueError, match=r"unknown keys \['wieght'\]"):
        rest_penalty(compose_cfg("+rest.wieght=1"), plants, meta)
    with pytest.raises(ValueError, match="rest.slack must lie in"):
        rest_penalty(compose_cfg("rest.weight=1", "rest.slack=2", "model.integral=true"),
                     plants, meta)  # fmt: skip
