"""Choose and check the LQI weights (Q, R) of the plant catalogue; write reports/lqi_table2.md.

Usage (from the repository root, with the project's virtual environment active)::

    python scripts/tune_lqi.py                       # evaluate the YAML weights, write report
    python scripts/tune_lqi.py --tune paper --write  # re-fit the 7 paper systems, update YAMLs
    python scripts/tune_lqi.py --tune others --write # re-tune the other 18 (well damped)
    python scripts/tune_lqi.py --tune cstr --tune two_tank   # named plants, print only

Every unit-step metric is computed as the data stage would see it: the LQI loop sampled at
the plant's ``dt`` (0.05 s; plant held by zero-order hold or RK4, forward-Euler integrator)
from rest, over ``HORIZON`` seconds, with :func:`generalist_control.metrics.step_metrics`.

Weights are searched as log10 of the n + 1 diagonal entries of Q with R = 1 (only Q / R
matters to the gain), by Nelder-Mead from the best three of a coarse grid of starts, then
restarted once from the best point. The search is deterministic and independent of the YAML
values, so re-running it reproduces them.

- Paper systems (Table 2 of the paper): minimise the squared log-ratio between our and the
  paper's LQI rise time, settling time, ISE, ITAE and u_max, plus an overshoot term.
- Other plants: settle (2 %) in about ``SETTLE_TARGET`` s (``SETTLE_TARGETS`` per plant)
  with overshoot under ~1 %, no slow creeping tail, and closed-loop poles no faster than
  ``POLE_LIMIT`` rad/s or the plant's fastest open-loop pole; ``INPUT_MIN`` keeps the
  absolute input of a plant above a bound in its +-20 steps (the two-tank pump flow).
- Both: the sampled loop (0.05 s) must keep a disk margin of at least ``MARGIN_MIN``, the
  robustness a too-fast continuous design loses when it is sampled.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import control
import numpy as np
from scipy.optimize import minimize

from generalist_control.common.paths import conf_dir
from generalist_control.evaluation.paper import TABLE2, TABLE2_COLUMNS, TABLE2_METRICS
from generalist_control.plants.catalog import available_plants, load_plant
from generalist_control.plants.definition import Plant, PlantConfigError
from generalist_control.simulation.lqi import (
    LQIController,
    LQIGains,
    design_lqi,
    sampled_closed_loop,
)
from generalist_control.simulation.metrics import step_metrics
from generalist_control.simulation.simulate import discretise, simulate

ROOT = Path(__file__).resolve().parents[1]
REPORT = ROOT / "reports" / "lqi_table2.md"

HORIZON = 15.0  # simulated seconds for the unit-step metrics
SETTLE_TARGET = 3.5  # s, target 2 % settling time for the non-paper plants
# Slower targets where the input would otherwise be unphysical at the +-20 steps: the
# two-tank pump cannot run backwards (and its absolute flow must stay above INPUT_MIN,
# cm^3/s, 10 % of the operating flow); a ship's rudder and turn rate are limited.
SETTLE_TARGETS = {"two_tank": 6.0, "ship_steering": 6.0}
INPUT_MIN = {"two_tank": 47.0}
POLE_LIMIT = 8.0  # rad/s, fastest closed-loop pole allowed without penalty (non-paper)
MARGIN_MIN = 0.5  # least disk margin of the sampled loop (gain [0.67, 2], phase 29 deg)
MARGIN_GRID = 400  # frequencies for the margin
ESS_SCALE = 1e-4  # relative steady-state error at the end of the run counted as 0.01 cost
MAX_EVALS = 400  # Nelder-Mead function evaluations per plant
SIMPLEX_STEP = 0.5  # decades: size of the initial Nelder-Mead simplex
START_DECADES = range(-6, 7, 2)  # log10 scales of the state and integral weights (starts)
N_STARTS = 3  # Nelder-Mead runs from the best grid starts
RESTARTS = 1  # Nelder-Mead restarts from the best point (a fresh simplex escapes stalls)

# The paper's Table 2 (tab:benchmark_performance): column labels and the LQI rows.
PAPER_COLUMNS = TABLE2_COLUMNS
# The paper's Table 2 LQI row, keyed by the paper's symbols (t_r, M_p, ...).
PAPER_LQI = {
    system: {TABLE2_METRICS[metric]: value for metric, value in row.items()}
    for system, row in TABLE2["LQI"].items()
}
# Relative importance of each metric in the paper fit (log-ratio terms) and overshoot scale.
FIT_WEIGHTS = dict(t_r=1.0, t_s=1.0, ISE=1.0, ITAE=1.0, u_max=1.0)
OVERSHOOT_SCALE = 2.0  # percentage points counted as one unit of error

KEYS = ("t_r", "M_p", "t_s", "e_ss", "ISE", "ITAE", "u_max")
_METRIC_OF = {symbol: metric for metric, symbol in TABLE2_METRICS.items()}
FAIL = 1e3


def with_weights(plant: Plant, q: Sequence[float], r: float) -> Plant:
    """A copy of ``plant`` with diagonal ``Q = diag(q)`` and ``R = r``."""
    return dataclasses.replace(plant, Q=np.diag(np.asarray(q, float)), R=np.array([[r]]))


def step(plant: Plant, amplitude: float = 1.0, horizon: float = HORIZON) -> dict[str, float]:
    """LQI step metrics (keys of :data:`KEYS`) from rest for a step of ``amplitude``."""
    steps = int(round(horizon / plant.dt))
    ctrl = LQIController(plant)
    tr = simulate(plant, ctrl, np.full((1, steps), float(amplitude)))
    m = step_metrics(tr.t, tr.y, tr.u, tr.r[:, -1])
    out = {k: float(m[_METRIC_OF[k]][0]) for k in KEYS}
    out["diverged"] = bool(tr.diverged[0])
    out["x_min"] = tr.x[0].min(axis=0) + plant.x_op
    out["x_max"] = tr.x[0].max(axis=0) + plant.x_op
    out["u_abs_min"] = float((tr.u[0] + plant.u_op).min())
    return out


def _unsettled(m: dict[str, float]) -> float | None:
    """A graded penalty for a run that diverged or did not settle, None otherwise.

    Runs that stay bounded but are too slow get ``10 + ISE``, so the search can still tell
    better from worse.
    """
    if m["diverged"] or not math.isfinite(m["ISE"]):
        return FAIL
    if not all(math.isfinite(m[k]) for k in ("t_r", "t_s")):
        return 10.0 + m["ISE"]
    return None


def paper_cost(m: dict[str, float], target: dict[str, float]) -> float:
    """Weighted squared log-ratio to the paper's metrics plus an overshoot term."""
    if (bad := _unsettled(m)) is not None:
        return bad
    cost = sum(w * math.log(m[k] / target[k]) ** 2 for k, w in FIT_WEIGHTS.items())
    return cost + ((m["M_p"] - target["M_p"]) / OVERSHOOT_SCALE) ** 2


def damped_cost(m: dict[str, float], settle_target: float) -> float:
    """Settle in about ``settle_target`` s with little overshoot and no slow creeping tail."""
    if (bad := _unsettled(m)) is not None:
        return bad
    cost = ((m["t_s"] - settle_target) / settle_target) ** 2
    cost += (max(0.0, m["M_p"] - 1.0) / 2.0) ** 2
    return cost + 0.01 * (m["e_ss"] / ESS_SCALE) ** 2


def sampled_stability_margin(plant: Plant, gains: LQIGains) -> float:
    """Disk (vector) margin ``min |1 + L(e^{jw dt})|`` of the sampled loop, cut at the input.

    ``L`` is the LQI gain times the zero-order-hold plant augmented with the Euler error
    integrator. The continuous LQI guarantees at least 1; sampling erodes it. A margin ``s``
    guarantees gain margins ``[1 / (1 + s), 1 / (1 - s)]`` and a phase margin of
    ``2 arcsin(s / 2)``.
    """
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    n = plant.order
    Phi = np.block([[Ad, np.zeros((n, 1))], [-plant.dt * plant.C, np.ones((1, 1))]])
    Gam = np.vstack([Bd, np.zeros((1, 1))])
    K = gains.K
    w = np.geomspace(1e-3, np.pi / plant.dt, MARGIN_GRID)
    z = np.exp(1j * w * plant.dt)
    eye = np.eye(n + 1)
    loop = np.array([(K @ np.linalg.solve(zk * eye - Phi, Gam))[0, 0] for zk in z])
    return float(np.abs(1.0 + loop).min())


def _input_penalty(plant: Plant, u_min: float) -> float:
    """Penalise the absolute input dropping below ``u_min`` in the +-20 (scaled) steps."""
    lowest = min(step(plant, a * plant.amplitude_scale)["u_abs_min"] for a in (20.0, -20.0))
    scale = max(abs(plant.u_op), 1.0)
    return 10.0 * (max(0.0, u_min - lowest) / scale) ** 2


def _margin_penalty(margin: float) -> float:
    """Zero above ``MARGIN_MIN``, then steeply quadratic."""
    return 10.0 * (max(0.0, MARGIN_MIN - margin) / MARGIN_MIN) ** 2


def _fast_pole_penalty(fastest_pole: float, pole_limit: float) -> float:
    """Zero up to ``pole_limit`` rad/s, then quadratic."""
    return (max(0.0, fastest_pole - pole_limit) / pole_limit) ** 2


def tune(plant: Plant) -> tuple[np.ndarray, float, float]:
    """Nelder-Mead over log10 diag(Q) with R = 1 from the best grid starts, then restarted.

    The start does not depend on the YAML values, so the result is reproducible.
    """
    target = PAPER_LQI.get(plant.name)
    settle_target = SETTLE_TARGETS.get(plant.name, SETTLE_TARGET)
    # A fast open-loop pole may stay where it is; only poles the design adds are penalised.
    pole_limit = max(POLE_LIMIT, float(np.abs(np.linalg.eigvals(plant.A)).max()))

    def objective(theta: np.ndarray) -> float:
        theta = np.clip(theta, -8.0, 8.0)
        candidate = with_weights(plant, 10.0**theta, 1.0)
        try:
            gains = design_lqi(candidate)
        except PlantConfigError:
            return FAIL
        m = step(candidate)
        cost = _margin_penalty(sampled_stability_margin(candidate, gains))
        if plant.name in INPUT_MIN:
            cost += _input_penalty(candidate, INPUT_MIN[plant.name])
        if target is not None:
            return cost + paper_cost(m, target)
        fastest = float(np.abs(gains.poles).max())
        return cost + damped_cost(m, settle_target) + _fast_pole_penalty(fastest, pole_limit)

    # Starts: a coarse grid of Q = diag(10^a q_x, 10^b) with q_x either all ones or only the
    # output's states (C^T C, the classic servo weighting); plants differ in units by orders
    # of magnitude, so Q = I alone can be far too cheap or too expensive a control.
    output_only = np.log10(np.where(np.abs(plant.C[0]) > 0, plant.C[0] ** 2, 1e-6))
    starts = [
        np.append(base + a, b)
        for base in (np.zeros(plant.order), output_only)
        for a in START_DECADES
        for b in START_DECADES
    ]
    start_costs = [objective(t) for t in starts]
    order = np.argsort(start_costs, kind="stable")[:N_STARTS]

    def descend(theta: np.ndarray) -> tuple[np.ndarray, float]:
        simplex = np.vstack([theta, theta + SIMPLEX_STEP * np.eye(theta.size)])
        res = minimize(
            objective,
            theta,
            method="Nelder-Mead",
            options={
                "maxfev": MAX_EVALS,
                "xatol": 1e-3,
                "fatol": 1e-6,
                "initial_simplex": simplex,
            },
        )
        return res.x, float(res.fun)

    # Local searches from the best few starts, then restarts from the overall best.
    theta, best = min((descend(starts[i]) for i in order), key=lambda r: r[1])
    for _ in range(RESTARTS):
        theta, best = descend(theta)
    q = _round_sig(10.0 ** np.clip(theta, -8.0, 8.0))
    return q, 1.0, float(objective(np.log10(q)))


def _round_sig(values: np.ndarray, digits: int = 3) -> np.ndarray:
    return np.array([float(f"{v:.{digits}g}") for v in values])


def _fmt(v: float) -> str:
    """Three significant digits, always with a decimal point (a YAML 1.1 float)."""
    text = f"{v:.3g}"
    mantissa, e, exponent = text.partition("e")
    if "." not in mantissa:
        mantissa += ".0"
    return mantissa + e + exponent


def write_weights(name: str, q: np.ndarray, r: float) -> None:
    """Replace the ``lqi:`` block (Q and R lines) of ``conf/plants/<name>.yaml``."""
    path = conf_dir() / "plants" / f"{name}.yaml"
    text = path.read_text()
    block = f"lqi:\n  Q: [{', '.join(_fmt(v) for v in q)}]\n  R: {_fmt(r)}\n"
    new, count = re.subn(r"lqi:\n  Q: [^\n]*\n  R: [^\n]*\n", block, text)
    if count != 1:
        raise SystemExit(f"{path}: could not find a unique 'lqi:' block with Q and R lines")
    path.write_text(new)


# --------------------------------------------------------------------------- reporting


def plant_properties(plant: Plant) -> dict[str, object]:
    """Open-loop stability and minimum-phase property of the (linearised) plant."""
    poles = np.linalg.eigvals(plant.A)
    zeros = control.ss(plant.A, plant.B, plant.C, 0).zeros()
    stable = bool(np.all(poles.real < -1e-9))
    marginal = bool(np.all(poles.real < 1e-9)) and not stable
    return {
        "poles": poles,
        "zeros": zeros,
        "stable": "yes" if stable else ("marginal" if marginal else "no"),
        "min_phase": "yes" if np.all(np.real(zeros) < 0) else "no",
    }


def _row(cells: Sequence[object]) -> str:
    return "| " + " | ".join(str(c) for c in cells) + " |"


def _num(v: float, digits: int = 2) -> str:
    return "n/a" if not math.isfinite(v) else f"{v:.{digits}f}"


def paper_table(results: dict[str, dict[str, float]]) -> list[str]:
    names = list(PAPER_COLUMNS)
    lines = [
        _row(["Metric", *[PAPER_COLUMNS[n] for n in names]]),
        _row(["---", *["---:"] * len(names)]),
    ]
    labels = dict(
        t_r="t_r (s)",
        M_p="M_p (%)",
        t_s="t_s (s)",
        e_ss="e_ss",
        ISE="ISE",
        ITAE="ITAE",
        u_max="u_max",
    )
    for k in KEYS:
        lines.append(_row([f"{labels[k]} paper", *[_num(PAPER_LQI[n][k]) for n in names]]))
        lines.append(_row([f"{labels[k]} ours", *[_num(results[n][k]) for n in names]]))
    return lines


def mismatch_lines(results: dict[str, dict[str, float]], tol: float = 0.10) -> list[str]:
    """Per paper system, the metrics more than ``tol`` (relative) or 1 point (M_p) off."""
    lines = []
    for name, column in PAPER_COLUMNS.items():
        ours, paper = results[name], PAPER_LQI[name]
        off = []
        for k in ("t_r", "t_s", "ISE", "ITAE", "u_max"):
            rel = ours[k] / paper[k] - 1.0
            if abs(rel) > tol:
                off.append(f"{k} {rel:+.0%}")
        if abs(ours["M_p"] - paper["M_p"]) > 1.0:
            off.append(f"M_p {ours['M_p'] - paper['M_p']:+.1f} points")
        verdict = ", ".join(off) if off else "all within 10 % (M_p within 1 point)"
        lines.append(f"- {column} ({name}): {verdict}")
    return lines


def catalogue_table(plants: list[Plant], results: dict[str, dict[str, float]]) -> list[str]:
    head = [
        "plant",
        "tag",
        "n",
        "linear",
        "OL stable",
        "min. phase",
        "t_r",
        "M_p %",
        "t_s",
        "e_ss",
        "ISE",
        "ITAE",
        "u_max",
        "fastest CL pole",
        "sampled rho",
        "disk margin",
    ]
    lines = [_row(head), _row(["---"] + ["---:"] * (len(head) - 1))]
    for p in plants:
        props = plant_properties(p)
        gains = design_lqi(p)
        rho = np.abs(np.linalg.eigvals(sampled_closed_loop(p, gains))).max()
        m = results[p.name]
        lines.append(
            _row(
                [
                    p.name,
                    p.tag,
                    p.order,
                    "yes" if p.is_linear else "no",
                    props["stable"],
                    props["min_phase"],
                    _num(m["t_r"]),
                    _num(m["M_p"], 1),
                    _num(m["t_s"]),
                    f"{m['e_ss']:.0e}",
                    _num(m["ISE"]),
                    _num(m["ITAE"]),
                    f"{m['u_max']:.3g}",
                    _num(float(np.abs(gains.poles).max()), 1),
                    _num(float(rho), 3),
                    _num(sampled_stability_margin(p, gains)),
                ]
            )
        )
    return lines


def nonlinear_table(plants: list[Plant]) -> list[str]:
    head = ["plant", "step", "t_s", "M_p %", "e_ss rel.", "state min", "state max", "min u"]
    lines = [_row(head), _row(["---"] + ["---:"] * (len(head) - 1))]
    for p in plants:
        if p.is_linear:
            continue
        for a in (0.2, -0.2, 1.0, -1.0, 20.0, -20.0):
            a = a * p.amplitude_scale
            m = step(p, a)
            lines.append(
                _row(
                    [
                        p.name,
                        f"{a:+g}",
                        _num(m["t_s"]),
                        _num(m["M_p"], 1),
                        f"{m['e_ss'] / abs(a):.1e}",
                        np.array2string(m["x_min"], precision=2, separator=", "),
                        np.array2string(m["x_max"], precision=2, separator=", "),
                        f"{m['u_abs_min']:.4g}",
                    ]
                )
            )
    return lines


def weights_table(plants: list[Plant]) -> list[str]:
    lines = [_row(["plant", "diag Q", "R"]), _row(["---", "---", "---:"])]
    for p in plants:
        q = ", ".join(_fmt(v) for v in np.diag(p.Q))
        lines.append(_row([p.name, f"[{q}]", _fmt(p.R[0, 0])]))
    return lines


NOTES = """\
## Notes on the comparison

- Metrics: rise time 10-90 %, overshoot in % of the final value, 2 % settling time, e_ss at
  the end of the run, ISE = int e^2 dt and ITAE = int t |e| dt over the {horizon:g} s run
  (trapezoidal rule), u_max = max |u|; sampled LQI at dt = 0.05 s from rest, unit step.
- The paper does not give its Q and R. Ours are diagonal (R = 1), fitted by Nelder-Mead on
  the squared log-ratio of t_r, t_s, ISE, ITAE and u_max plus an overshoot term (equal
  weights), subject to a disk margin of about 0.5 or more for the loop sampled at 0.05 s.
- Unst., NMP, H.Act, B-747 and TMS match on every metric within a few per cent, so the
  paper's metric definitions (including ISE/ITAE over a run of this length) agree with ours.
- Yaw: the paper's u_max = 1.10 deg of rudder per deg of heading is reachable with Prestero's
  coefficients at 1.54 m/s only with a fast (~19 rad/s) sway loop: Q = diag(1430, 1.14, 469,
  482) gives t_r 2.80, M_p 0.82, t_s 4.35, ISE 1.09, ITAE 2.17, u_max 1.10, but its sampled
  disk margin is 0.40. We keep the margin near 0.5 and accept u_max 0.97 (-12 %). The
  cross-flow drag changes the closed-loop response only slightly between 0.2 and 20 degree
  steps (see the nonlinear table).
- Crazyflie: the paper gives no Crazyflie model; ours (m = 27 g, estimated linear drag)
  reaches u_max 0.08 N and t_s 4.05 s only with a ~37 rad/s velocity loop (Q = diag(0.825,
  1.02, 2.48): t_r 1.90, M_p 2.1, t_s 4.25, ISE 0.91, ITAE 1.29, u_max 0.079) whose sampled
  loop has a mode at z = -0.95 and a disk margin of 0.03: unusable at 20 Hz. With the margin
  kept near 0.5 the fit is faster with less peak thrust (t_r -19 %, u_max -39 %).
- Time-scaled plants (see conf/plants/README.md): hvac_two_zone (minutes),
  magnetic_levitation (x10) and quarter_car (x5); their times are model times.
"""


def write_report(plants: list[Plant], results: dict[str, dict[str, float]]) -> str:
    text = [
        "# LQI expert: unit-step metrics (generated by scripts/tune_lqi.py)",
        "",
        "Do not edit by hand: run `python scripts/tune_lqi.py` to regenerate.",
        "",
        "## Paper systems: ours vs the paper's LQI row (Table 2, tab:benchmark_performance)",
        "",
        *paper_table(results),
        "",
        "Metrics more than 10 % from the paper (M_p: more than 1 percentage point):",
        "",
        *mismatch_lines(results),
        "",
        NOTES.format(horizon=HORIZON),
        f"## All {len(plants)} plants",
        "",
        "OL stable: open-loop poles of the (linearised) plant all in the open left half-plane "
        "(marginal: poles on the imaginary axis, none in the right half-plane). Minimum phase: "
        "no transmission zero with Re >= 0. Fastest CL pole: largest |s| of the continuous LQI "
        "closed loop (rad/s); sampled rho: spectral radius of the 0.05 s sampled loop; "
        "disk margin: min |1 + L| of the sampled loop cut at the plant input "
        "(continuous LQI: >= 1).",
        "",
        *catalogue_table(plants, results),
        "",
        "## Nonlinear plants: steps of different size (x amplitude_scale)",
        "",
        "States are absolute (operating point included); min u is the smallest absolute input "
        "(for two_tank the pump flow, which should stay positive).",
        "",
        *nonlinear_table(plants),
        "",
        "## Weights (diagonal Q on [x; z], scalar R)",
        "",
        *weights_table(plants),
        "",
    ]
    REPORT.parent.mkdir(parents=True, exist_ok=True)
    out = "\n".join(text)
    REPORT.write_text(out)
    return out


def _select(names: Sequence[str]) -> list[str]:
    chosen: list[str] = []
    for n in names:
        if n == "paper":
            chosen += list(PAPER_LQI)
        elif n == "others":
            chosen += [p for p in available_plants() if p not in PAPER_LQI]
        elif n == "all":
            chosen += available_plants()
        else:
            chosen.append(n)
    return list(dict.fromkeys(chosen))


def main(argv: Sequence[str] | None = None, log: Callable[[str], None] = print) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tune", action="append", default=[], help="plant, paper, others, all")
    parser.add_argument("--write", action="store_true", help="write tuned weights to YAML")
    args = parser.parse_args(argv)

    for name in _select(args.tune):
        plant = load_plant(name)
        q, r, cost = tune(plant)
        log(f"{name}: cost {cost:.4f}\n  lqi:\n    Q: [{', '.join(_fmt(v) for v in q)}]")
        log(f"    R: {_fmt(r)}")
        if args.write:
            write_weights(name, q, r)
    if args.tune and not args.write:
        return 0

    plants = sorted((load_plant(n) for n in available_plants()), key=lambda p: p.tag)
    results = {p.name: step(p) for p in plants}
    log(write_report(plants, results))
    log(f"\nwrote {REPORT.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
