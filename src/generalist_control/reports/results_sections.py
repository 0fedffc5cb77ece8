"""The sections of the results page: parsed report files in, markdown lines out."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

__all__ = ["FIGURES", "MAX_ROWS", "SECTIONS", "Recipe", "fmt", "number", "policy_cell", "table"]

MAX_ROWS = 20
#: The figures' folder, relative to the page.
FIGURES = "figures"


@dataclass(frozen=True)
class Recipe:
    """One recipe of the page: ``kind`` picks its section, ``files`` maps a role to a path."""

    key: str
    title: str
    kind: str
    command: str
    files: Mapping[str, str]


def number(value: Any) -> float | None:
    """A number from JSON or CSV text; None for anything else or an empty cell."""
    if isinstance(value, bool) or value is None:
        return None
    try:
        return float(value)
    except (TypeError, ValueError):
        return None


def fmt(value: Any) -> str:
    """A figure as the page writes it: ``1.0031``, ``9.89e-04``, ``56,484``, ``n/a``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return "n/a" if value is None or value == "" else _text(value)
    if isinstance(value, int):
        return f"{value:,}"
    if math.isnan(value):
        return "n/a"
    if math.isinf(value) or value == 0:
        return str(value).replace(".0", "")
    if 0.01 <= abs(value) < 1000:  # trailing zeros only where the value is that short
        text = f"{value:.4f}"
        return text.rstrip("0").rstrip(".") if round(value, 4) == value else text
    return f"{value:,.0f}" if abs(value) >= 1000 else f"{value:.2e}"


def _text(value: Any, limit: int = 120) -> str:
    """Text for one table cell or line: no newline, pipe or backtick; at most ``limit``."""
    text = " ".join(str(value).split()).replace("|", "/").replace("`", "'")
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _verdict(value: Any) -> str:
    return "not measured" if value is None else ("pass" if value else "**fail**")


def _names(values: Any, limit: int = 5) -> str:
    """A short list of names: ``a, b, c and 4 more``; ``none`` when empty."""
    names = [_text(v, 40) for v in (values or [])]
    more = f" and {len(names) - limit} more" if len(names) > limit else ""
    return ", ".join(names[:limit]) + more if names else "none"


def table(
    header: Sequence[str], rows: Sequence[Sequence[Any]], source: str | None = None
) -> list[str]:
    """A markdown table; with ``source``, at most :data:`MAX_ROWS` rows, a last one naming it."""
    keep = rows if source is None else rows[:MAX_ROWS]
    cells = [[str(c).replace("|", "/").replace("\n", " ") for c in row] for row in keep]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in cells]
    if len(rows) > len(keep):
        rest = [""] * (len(header) - 1)
        lines.append("| " + " | ".join([f"{len(rows) - MAX_ROWS} more in `{source}`", *rest]))
    return lines


def _head(recipe: Recipe, summary: Mapping[str, Any]) -> list[str]:
    """Heading, command, reports; the date and machine where the summary records them."""
    prov = summary.get("provenance")
    prov = prov if isinstance(prov, Mapping) else {}
    lines = [f"## {recipe.title}", "", f"- command: `{recipe.command}`"]
    lines += [f"- {k}: {_text(prov[k])}" for k in ("date", "machine") if prov.get(k)]
    if prov.get("command"):
        lines.append(f"- recorded command: `{_text(prov['command'], 300)}`")
    lines.append("- reports: " + ", ".join(f"`{p}`" for p in recipe.files.values()))
    return [*lines, ""]


def _training(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """One line of the training's figures, or one that says the file is absent."""
    path = recipe.files.get("training")
    if path is None:
        return []
    m = data.get("training")
    if not isinstance(m, Mapping):
        return [f"Training figures: `{path}` is not here (written by the command above).", ""]
    parts = [
        f"{fmt(m.get('epochs'))} epochs",
        f"{fmt(m.get('n_parameters'))} parameters",
        f"val/loss {fmt(m.get('val/loss'))}",
        f"closed-loop validation: {fmt(m.get('closed_loop/diverged'))} plants diverged",
    ]
    return [f"Training (`{path}`): " + ", ".join(parts) + ".", ""]


def _setpoint(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """Plants that settle at a constant reference, and the largest radius of GC's loop."""
    rows, path = data.get("setpoint"), recipe.files.get("setpoint")
    if not rows:
        return []
    settle = sum(str(r.get("settles")) == "True" for r in rows)
    radii = [(number(r.get("radius_GC")), r) for r in rows]
    finite = [(v, r) for v, r in radii if v is not None]
    line = f"At rest (`{path}`): {settle} of {len(rows)} plants settle at a constant reference"
    if finite:
        value, worst = max(finite, key=lambda item: item[0])
        unstable = sum(v >= 1.0 for v, _ in finite)
        line += (
            f"; {unstable} with a loop of spectral radius >= 1 there; largest "
            f"{fmt(value)} ({_text(worst.get('system'), 40)}, LQI's "
            f"{fmt(number(worst.get('radius_LQI')))})"
        )
    return [line + ".", ""]


def _worst(fig: Mapping[str, Any], key: str) -> str:
    """``1.0031 (plant)`` from ``worst_<key>_ratio`` and ``worst_<key>_system``."""
    name = f"worst_{key}_ratio" if key != "ess" else "worst_relative_ess_GC"
    system = fig.get(f"worst_{key}_system" if key != "ess" else "worst_relative_ess_system")
    if name not in fig:
        return ""
    return fmt(fig[name]) + (f" ({_text(system, 40)})" if system else "")


def _scenario_rows(summary: Mapping[str, Any]) -> list[list[str]]:
    """Per scenario: the worst plant's ratios and GC's diverged runs."""
    div = summary.get("diverged") or {}

    def lost(scen: str) -> str:
        return fmt(sum(int((div.get(c) or {}).get(scen, 0)) for c in ("GC", "GC-AW")))

    rows = [
        [f"`{scen}`", _worst(f, "ISE"), _worst(f, "ITAE"), "", _worst(f, "ess"), lost(scen)]
        for scen, f in (summary.get("ratios") or {}).items()
    ]
    for scen, f in (summary.get("tracking") or {}).items():
        rows.append([f"`{scen}`", "", "", _worst(f, "RMSE"), "", lost(scen)])
    for scen, f in (summary.get("anti_windup") or {}).items():
        rows.append([f"`{scen}`, GC-AW / LQI-AW", _worst(f, "ISE"), "", "", "", ""])
    return rows


def _bar_line(bar: Mapping[str, Any]) -> list[str]:
    """The quality bar's verdicts on one line."""
    checked = [v for v in bar.values() if v is not None]
    verdicts = ", ".join(f"`{_text(k, 40)}` {_verdict(v)}" for k, v in list(bar.items())[:12])
    count = f"{sum(bool(v) for v in checked)} of {len(checked)} passed"
    return [f"Quality bar (`docs/evaluation.md`): {count}: {verdicts or 'none'}.", ""]


def _tag_free_bar(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """The tag-free bar (``bar.json``) on one line, or that the file is absent."""
    path, bar = recipe.files.get("bar"), data.get("bar")
    if path is None:
        return []
    if not isinstance(bar, Mapping):
        return [f"Tag-free bar: `{path}` is not here (written by the command above).", ""]
    return [
        f"Tag-free bar (`{path}`): {'met' if bar.get('met') else '**not met**'}; "
        f"{fmt(bar.get('passed'))} of {fmt(bar.get('plants'))} plants within the unit-step ISE "
        f"ratio {fmt(bar.get('ise_ratio_bar'))} (at least {fmt(bar.get('min_plants'))} "
        f"required); no divergence: {_verdict(bar.get('no_divergence'))}; diverged: "
        f"{_names(bar.get('diverged'))}; missed: {_names(bar.get('missing'))}.",
        "",
    ]


_SCENARIO_HEADER = ("scenario", "worst ISE ratio", "worst ITAE ratio", "worst RMSE ratio",
                    "worst relative e_ss of GC", "GC runs diverged")  # fmt: skip


def _evaluation_section(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """Bar verdicts and the worst plant's GC/LQI ratios per scenario."""
    summary, source = data["summary"], recipe.files["summary"]
    lines = [*_head(recipe, summary), *_training(recipe, data)]
    lines += _bar_line(summary.get("quality_bar") or {})
    lines += ["Worst plant's GC/LQI ratio of the mean over its runs, per scenario:", ""]
    lines += [*table(_SCENARIO_HEADER, _scenario_rows(summary), source), ""]
    return lines + _setpoint(recipe, data) + _tag_free_bar(recipe, data)


def _bar_cell(bar: Any) -> str:
    """``value 1.004, limit 1.1: pass`` from one bar of a variants summary."""
    if not isinstance(bar, Mapping):
        return ""
    figures = [
        f"{_text(k, 30)} {fmt(v)}"
        for k, v in bar.items()
        if k != "pass" and not isinstance(v, (Mapping, list))
    ]
    return ", ".join(figures[:4]) + f": {_verdict(bar.get('pass'))}"


def _variants_section(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """The bars on the test and held-out draws, and the worst plants."""
    summary, source = data["summary"], recipe.files["summary"]
    held = summary.get("validation") or {}
    test_bars, held_bars = summary.get("bars") or {}, held.get("bars") or {}
    rows = [
        [f"`{_text(name, 40)}`", _bar_cell(test_bars.get(name)), _bar_cell(held_bars.get(name))]
        for name in dict.fromkeys([*test_bars, *held_bars])
    ]
    rows.append(["all bars", _verdict(summary.get("pass")), _verdict(held.get("pass"))])
    header = ("bar", "test draw", f"held-out draw (seed {_text(held.get('seed'), 20)})")
    per_plant = summary.get("per_plant") or {}
    worst = sorted(
        ((number(p.get("worst_GC_over_oracle")), name) for name, p in per_plant.items()),
        key=lambda item: -(item[0] if item[0] is not None else -math.inf),
    )[:3]
    names = ", ".join(f"{_text(n, 40)} {fmt(v)}" for v, n in worst) or "none"
    lines = [*_head(recipe, summary), *_training(recipe, data)]
    lines += ["GC's unit-step ISE over each unseen variant's own LQI (the oracle):", ""]
    lines += [*table(header, rows, source), ""]
    lines += [f"Worst plants (their worst variant, test draw): {names}.", ""]
    return lines + _setpoint(recipe, data)


def _ablation_rows(data: Mapping[str, Any]) -> list[list[str]]:
    """Per sweep point of ``runs.csv``: parameters, loss, mean MSE, diverged plants, run."""
    configs = data["summary"].get("configs") or {}
    rows = []
    for r in data.get("runs") or []:
        d, m = number(r.get("hidden")), number(r.get("experts"))
        ok = r.get("status") == "ok" and d is not None and m is not None
        cfg = configs.get(f"d={d:g},M={m:g}") if d is not None and m is not None else None
        cfg = cfg if isinstance(cfg, Mapping) else {}
        n_par = number(r.get("n_parameters"))
        cells = [
            f"{int(n_par):,}" if n_par is not None else "n/a",
            fmt(number(r.get("final_train_loss"))),
            fmt(number(cfg.get("mse_mean"))),
            fmt(number(r.get("closed_loop_diverged"))),
            f"`{_text(r.get('run_id'))[:8]}`",
        ]
        status = _text(r.get("status") or "no run", 30)
        cells = cells if ok else [status, "", "", "", ""]
        rows.append([_text(r.get("label"), 20), fmt(d), fmt(m), *cells])
    return rows


_ABLATION_HEADER = ("point", "d", "M", "parameters", "final train loss", "mean closed-loop MSE",
                    "plants diverged", "run")  # fmt: skip


def _claims(recipe: Recipe, summary: Mapping[str, Any]) -> list[str]:
    """The paper's claims beside ours, with the verdicts (``summary['claims']``)."""
    claims = [c for c in summary.get("claims") or [] if isinstance(c, Mapping)]
    if not claims:
        return []
    counts = summary.get("claims_verdicts") or {}
    tally = ", ".join(f"{_text(n, 10)} {_text(v, 30)}" for v, n in counts.items())
    rows = [
        [_text(c.get("claim"), 80), _text(c.get("paper"), 20), _text(c.get("ours"), 60),
         _text(c.get("verdict"), 30)]
        for c in claims
    ]  # fmt: skip
    source = recipe.files["summary"].replace("summary.json", "claims.csv")
    lines = [f"The paper's Section 7, claim by claim ({_text(tally, 200)}; rules and notes in "
             f"`{source}`):", ""]  # fmt: skip
    return [*lines, *table(("claim", "paper", "ours", "verdict"), rows, source), ""]


#: What each ablation figure shows (its alt text on the page).
FIGURE_TITLES = {
    "mse_hidden": "closed-loop output MSE per plant by d",
    "loss_hidden": "final training loss by d, each seed, the paper's",
    "mse_experts": "closed-loop output MSE per plant by M",
    "loss_experts": "final training loss by M, each seed, the paper's",
    "params_vs_mse": "parameters against mean closed-loop MSE",
    "gate_weights": "mean gate weight per plant and expert, M = 5",
}


def _ablation_figures(recipe: Recipe, names: Sequence[str]) -> list[str]:
    """The figures drawn from the recipe's tables, two to a line."""
    links = [f"![{recipe.key}: {FIGURE_TITLES[n]}]({FIGURES}/{recipe.key}/{n}.png)" for n in names]
    folder = recipe.files["summary"].rsplit("/", 1)[0]
    lines = [f"Figures (from `{folder}/runs.csv`, `points.csv` and `gate_weights.csv`):", ""]
    for i in range(0, len(links), 2):
        lines += [" ".join(links[i : i + 2]), ""]
    return lines


def _ablation_section(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """Per point its parameters, losses, mean MSE, diverged plants; the figures; the claims."""
    summary = data["summary"]
    lines = [*_head(recipe, summary)]
    if "runs" in data:
        lines += [*table(_ABLATION_HEADER, _ablation_rows(data), recipe.files["runs"]), ""]
    else:
        lines += [f"Per-point figures: `{recipe.files.get('runs')}` is not here.", ""]
    lines += [f"No run for: {_names(summary.get('missing'), 10)}.", ""]
    lines += _ablation_figures(recipe, data.get("figures") or [])
    return lines + _claims(recipe, summary)


def policy_cell(figures: Mapping[str, Any] | None) -> str:
    """``ISE / RMSE / diverged`` of one policy on one held-out plant."""
    f = figures or {}
    return (
        f"{fmt(number(f.get('ISE_ratio')))} / {fmt(number(f.get('RMSE_ratio_worst')))}"
        f" / {fmt(f.get('diverged_runs'))}"
    )


def _unseen_row(name: str, entry: Mapping[str, Any]) -> list[str]:
    """One held-out plant: its class, the adaptation, and per policy ISE / RMSE / diverged."""
    cls = entry.get("class") or {}
    kinds = [k for k, on in (("unstable", cls.get("open_loop_unstable")),
                             ("NMP", cls.get("non_minimum_phase")),
                             ("nonlinear", cls.get("nonlinear"))) if on]  # fmt: skip
    damping = number(cls.get("min_damping"))
    if damping is not None and damping < 0.2:
        kinds.append(f"zeta {fmt(damping)}")
    demos = entry.get("demonstrations") or {}
    wall = number(entry.get("adaptation_wall_s"))
    cells = [f"`{_text(name, 40)}`", ", ".join([f"order {fmt(cls.get('order'))}", *kinds]),
             "n/a" if wall is None else f"{wall:.0f}",
             f"{fmt(demos.get('windows'))} + {fmt(demos.get('dagger_windows'))}"]  # fmt: skip
    policies = entry.get("policies") or {}
    return cells + [policy_cell(policies.get(k)) for k in ("adapted", "zero_shot", "trained_with")]


_UNSEEN_HEADER = ("held-out plant", "class", "adaptation s", "windows + DAgger",
                  "adapted: ISE / RMSE / diverged", "zero-shot (tag-free)",
                  "trained with it")  # fmt: skip


def _unseen_section(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    """Per held-out plant the three policies' worst ratios to its LQI; then the bar."""
    summary, source = data["summary"], recipe.files["summary"]
    held = summary.get("held_out") or {}
    rows = [_unseen_row(name, e) for name, e in held.items() if isinstance(e, Mapping)]
    lines = [*_head(recipe, summary), *_training(recipe, data)]
    lines += [
        "Per held-out plant, each policy's unit-step ISE ratio and worst tracking RMSE ratio "
        "to the plant's LQI, and its diverged runs over every scenario:",
        "",
    ]
    lines += [*table(_UNSEEN_HEADER, rows, source), ""]
    bars = summary.get("bars") or {}
    if bars:
        cells = [f"`{_text(k, 30)}` {_bar_cell(v)}" for k, v in bars.items()]
        lines += [f"Bar on the adapted policies: {'; '.join(cells)}; "
                  f"all: {_verdict(summary.get('pass'))}.", ""]  # fmt: skip
    return lines


SECTIONS = {
    "evaluation": _evaluation_section,
    "unseen": _unseen_section,
    "variants": _variants_section,
    "ablation": _ablation_section,
}
