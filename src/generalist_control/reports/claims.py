"""The paper's Section 7, claim by claim, beside our runs: ours, the paper's, and a verdict.

The verdicts are explained in docs/pipeline.md.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import pandas as pd

from generalist_control.reports.figures import fmt_value
from generalist_control.reports.report_settings import Tolerance
from generalist_control.reports.runs import NO_RUN, NOT_AVAILABLE, ByConfig, RunPoint

__all__ = [
    "CLAIMS",
    "NOT_COMPARABLE",
    "RULES",
    "Claim",
    "judge_claims",
    "verdict_counts",
]

Config = tuple[int, int]
REPRODUCES, FAILS, SEEDS = "reproduces", "does not reproduce", "seed-dependent"
NOT_COMPARABLE = "not comparable"

#: The rule of each kind of claim, as the report states it.
RULES = {
    "loss": "within a factor {factor:g} of the paper's",
    "mse": "within a factor {factor:g} of the paper's",
    "ratio": "within a factor {factor:g} of the paper's (runs of one seed paired)",
    "count": "within {count_relative:.0%} of the paper's",
    "order": "each run of the first configuration below every run of the others",
    "share": "dominant expert's share within {share_pp:g} percentage points of the paper's",
    "pattern": "holds for the dominant experts",
}

_LOSS_UNITS = (
    "our default recipe's loss is in per-plant RMS-normalised units with per-window scaling, "
    "over five more reference families and DAgger's windows; the paper's is not"
)
_NETWORK = "the default network adds a skip path and the error-integral channel"
_MSE_NOTE = (
    "ours: GC-vs-LQI output MSE, unit step x amplitude_scale, 15 s; the paper does not "
    "define its reference"
)
_LOSS_NOTE = "per-plant RMS-normalised controls (the paper does not state its normalisation)"
_GATE_NOTE = "ours: mean gate weight over a closed-loop unit step; expert numbers are arbitrary"


@dataclass(frozen=True)
class Claim:
    """One claim of the paper's Section 7: a figure (a float) or finding (a str) of the paper."""

    key: str
    text: str
    kind: str  #: a key of :data:`RULES`
    #: one for a figure, (numerator, denominator) for a ratio, (best, others...) for an order
    configs: tuple[Config, ...]
    paper: float | str
    plant: str | None = None
    default_reason: str | None = None  #: why not comparable for the default recipe
    note: str = ""


def _loss(key: str, config: Config, value: float) -> Claim:
    d, m = config
    return Claim(
        f"loss_{key}", f"final training loss, d={d}, M={m}", "loss", (config,), value,
        default_reason=_LOSS_UNITS, note=_LOSS_NOTE,
    )  # fmt: skip


def _mse(key: str, plant: str, config: Config, value: float) -> Claim:
    d, m = config
    text = f"{plant} output MSE, d={d}, M={m}"
    return Claim(f"mse_{key}", text, "mse", (config,), value, plant, note=_MSE_NOTE)


def _share(plant: str, expert: int, value: float) -> Claim:
    text = f"gate: expert {expert} dominates {plant}, d=32, M=5"
    return Claim(f"gate_{plant}", text, "share", ((32, 5),), value, plant, note=_GATE_NOTE)


#: The claims, in the order of the paper's Section 7.
CLAIMS: tuple[Claim, ...] = (
    _loss("d16", (16, 3), 1.02e-2),
    _loss("d32", (32, 3), 9.43e-4),
    _loss("d64", (64, 3), 4.01e-4),
    Claim("loss_ratio_d16", "training loss d=16 over d=32 (\"more than an order of magnitude\")",
          "ratio", ((16, 3), (32, 3)), 1.02e-2 / 9.43e-4, note="a ratio of losses of one recipe"),
    Claim("loss_ratio_d64", "training loss d=64 over d=32 (the lowest)", "ratio",
          ((64, 3), (32, 3)), 4.01e-4 / 9.43e-4, note="a ratio of losses of one recipe"),
    Claim("params_d32", "parameters, d=32, M=3", "count", ((32, 3),), 59_180.0,
          default_reason=_NETWORK),
    Claim("params_d64", "parameters, d=64, M=3 (\"232K\")", "count", ((64, 3),), 232_000.0,
          default_reason=_NETWORK),
    _mse("crazyflie_d16", "crazyflie_altitude", (16, 3), 1.35),
    _mse("crazyflie_d32", "crazyflie_altitude", (32, 3), 5.9e-2),
    _mse("crazyflie_d64", "crazyflie_altitude", (64, 3), 1.44e-1),
    Claim("mse_ratio_crazyflie_d16", "crazyflie_altitude MSE d=16 over d=32", "ratio",
          ((16, 3), (32, 3)), 1.35 / 5.9e-2, "crazyflie_altitude"),
    _mse("crazyflie_m1", "crazyflie_altitude", (32, 1), 3.98),
    Claim("mse_ratio_crazyflie_m1", "crazyflie_altitude MSE M=1 over M=3 (\"two orders\")",
          "ratio", ((32, 1), (32, 3)), 3.98 / 5.9e-2, "crazyflie_altitude"),
    _loss("m5", (32, 5), 5.87e-4),
    Claim("loss_ratio_m5", "training loss M=5 over M=3 (\"marginal improvement\")", "ratio",
          ((32, 5), (32, 3)), 5.87e-4 / 9.43e-4, note="a ratio of losses of one recipe"),
    _mse("hvac_m5", "hvac_two_zone", (32, 5), 5.18e-4),
    Claim("order_hvac_m5", "hvac_two_zone MSE lowest at M=5 of M in {1, 3, 5}", "order",
          ((32, 5), (32, 1), (32, 3)), "M=5 lowest", "hvac_two_zone"),
    _share("cstr", 1, 0.45),
    _share("damped_oscillator", 1, 0.46),
    _share("boeing747", 4, 0.98),
    _share("crazyflie_altitude", 4, 0.95),
    Claim("gate_pattern", "gate: one expert dominates cstr and damped_oscillator, another "
          "boeing747 and crazyflie_altitude", "pattern", ((32, 5),),
          "experts 1 and 4", note=_GATE_NOTE),
)  # fmt: skip


def _verdict(passed: Sequence[bool]) -> str:
    if all(passed):
        return REPRODUCES
    return FAILS if not any(passed) else SEEDS


def _within(claim: Claim, value: float, tol: Tolerance) -> bool:
    paper = float(claim.paper)
    if not math.isfinite(value) or value <= 0:
        return False
    if claim.kind == "count":
        return abs(value - paper) <= tol.count_relative * paper
    if claim.kind == "share":
        return abs(value - paper) <= tol.share_points
    return paper / tol.factor <= value <= paper * tol.factor


def _figure(kind: str, plant: str | None, p: RunPoint) -> float | None:
    """A run's figure: its final training loss, parameter count or a plant's MSE."""
    if kind == "loss":
        return p.train_loss
    if kind == "count":
        return None if p.n_parameters is None else float(p.n_parameters)
    return p.mse.get(str(plant))


def _seed(p: RunPoint) -> str:
    return "run" if p.seed is None else f"s{p.seed}"


def _values(claim: Claim, by_config: ByConfig) -> list[tuple[str, float | None]]:
    """``(seed, value)`` per seed of a figure, or per pair of runs of one seed of a ratio."""
    runs = [list(by_config[c]) for c in claim.configs]
    if claim.kind != "ratio":
        return [(_seed(p), _figure(claim.kind, claim.plant, p)) for p in runs[0]]
    kind = "mse" if claim.plant else "loss"
    den = {p.seed: p for p in runs[1]}
    pairs = [(p, den[p.seed]) for p in runs[0] if p.seed in den] or [(runs[0][0], runs[1][0])]
    out = []
    for a, b in pairs:
        x, y = _figure(kind, claim.plant, a), _figure(kind, claim.plant, b)
        label = _seed(a) if a.seed == b.seed else f"{_seed(a)}/{_seed(b)}"
        out.append((label, None if x is None or not y else x / y))
    return out


def _judge_values(claim: Claim, by_config: ByConfig, tol: Tolerance) -> tuple[str, str]:
    values = _values(claim, by_config)
    ours = ", ".join(f"{fmt_value(v)} ({s})" for s, v in values)
    if any(v is None for _, v in values):
        return NOT_AVAILABLE, ours
    return _verdict([_within(claim, v, tol) for _, v in values if v is not None]), ours


def _judge_order(claim: Claim, by_config: ByConfig) -> tuple[str, str]:
    best, *others = ([p.mse.get(str(claim.plant)) for p in by_config[c]] for c in claim.configs)
    rivals = [v for group in others for v in group]
    if any(v is None for v in [*best, *rivals]):
        return NOT_AVAILABLE, "a run has no score"
    pairs = [all(b < r for r in rivals) for b in best]  # type: ignore[operator]
    ours = "; ".join(
        f"d={d}, M={m}: "
        + ", ".join(fmt_value(p.mse[str(claim.plant)]) for p in by_config[(d, m)])
        for d, m in claim.configs
    )
    return _verdict(pairs), ours


def _dominant(gates: pd.DataFrame, plant: str) -> tuple[str, float] | None:
    if plant not in gates.index:
        return None
    row = gates.loc[plant]
    return str(row.idxmax()).replace("expert_", "expert "), float(row.max())


def _judge_gates(claim: Claim, gates: pd.DataFrame | None, tol: Tolerance) -> tuple[str, str]:
    if gates is None:
        return NO_RUN, "no M=5 model"
    if claim.kind == "share":
        dom = _dominant(gates, str(claim.plant))
        if dom is None:
            return NOT_AVAILABLE, "not trained on it"
        return (REPRODUCES if _within(claim, dom[1], tol) else FAILS), f"{dom[0]}: {dom[1]:.0%}"
    pairs = (("cstr", "damped_oscillator"), ("boeing747", "crazyflie_altitude"))
    doms = [[_dominant(gates, p) for p in pair] for pair in pairs]
    if any(d is None for pair in doms for d in pair):
        return NOT_AVAILABLE, "not trained on every plant"
    names = [[d[0] for d in pair if d] for pair in doms]
    ours = "; ".join(f"{'/'.join(p)}: {'/'.join(n)}" for p, n in zip(pairs, names, strict=True))
    ok = names[0][0] == names[0][1] and names[1][0] == names[1][1] and names[0][0] != names[1][0]
    return (REPRODUCES if ok else FAILS), ours


def _judge(
    claim: Claim, by_config: ByConfig, gates: pd.DataFrame | None, tol: Tolerance
) -> tuple[str, str]:
    """A claim's verdict and our figures, before comparability is considered."""
    if claim.kind in ("share", "pattern"):
        return _judge_gates(claim, gates, tol)
    absent = [c for c in claim.configs if not by_config.get(c)]
    if absent:
        return NO_RUN, f"{NO_RUN}: " + ", ".join(f"d={d}, M={m}" for d, m in absent)
    if claim.kind == "order":
        return _judge_order(claim, by_config)
    return _judge_values(claim, by_config, tol)


def judge_claims(
    by_config: ByConfig,
    gates: pd.DataFrame | None,
    tolerance: Tolerance,
    recipe: str,
) -> pd.DataFrame:
    """Every claim beside our figures, with its verdict: ``claim, key, paper, ours, rule, ...``.

    ``by_config``: (d, M) -> its runs, one per seed; ``gates``: the M = 5 model's mean gate
    weights (plants x ``expert_<i>``) or None; ``recipe``: ``default`` or ``paper`` (some
    figures are comparable only for the paper's).
    """
    rows = []
    for claim in CLAIMS:
        verdict, ours = _judge(claim, by_config, gates, tolerance)
        note = claim.note
        if recipe != "paper" and claim.default_reason and verdict not in (NO_RUN, NOT_AVAILABLE):
            verdict, note = NOT_COMPARABLE, claim.default_reason
        if claim.kind == "share":
            paper = f"{float(claim.paper):.0%}"
        else:
            paper = claim.paper if isinstance(claim.paper, str) else fmt_value(claim.paper)
        rule = RULES[claim.kind].format(
            share_pp=100 * tolerance.share_points, **dataclasses.asdict(tolerance)
        )
        rows.append((claim.text, claim.key, paper, ours, rule, verdict, note))
    cols = ["claim", "key", "paper", "ours", "rule", "verdict", "note"]
    return pd.DataFrame(rows, columns=cols)


def verdict_counts(table: pd.DataFrame) -> dict[str, int]:
    """How many claims got each verdict."""
    return {str(k): int(v) for k, v in table["verdict"].value_counts(sort=False).items()}
