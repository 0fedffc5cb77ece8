"""The results page's held-out section, with the zero-shot routes and the family draw."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from generalist_control.reports.results_sections import SECTIONS as BASE_SECTIONS
from generalist_control.reports.results_sections import Recipe, fmt, number, policy_cell, table

__all__ = ["SECTIONS", "routes_lines"]

_HEADER = ("held-out plant", "model card: ISE / RMSE / diverged", "in context")


def _ratio(value: Any) -> str:
    """A draw plant's ratio; none (JSON's ``null`` for ``inf``): a run diverged."""
    return "diverged" if value is None else fmt(number(value))


def _draw_lines(draw: Mapping[str, Any], source: str) -> list[str]:
    ise = draw.get("ISE_ratio") or {}
    lines = [
        f"The model card route on {fmt(draw.get('plants'))} plants of family "
        f"`{draw.get('family')}` drawn from seed {draw.get('seed')} (no training saw it), every "
        f"scenario: {fmt(draw.get('diverged_runs'))} diverged runs on "
        f"{fmt(draw.get('diverged_plants'))} plants; unit-step ISE ratio to each plant's LQI "
        f"median {_ratio(ise.get('median'))}, 95th percentile "
        f"{_ratio(ise.get('p95'))}, worst {_ratio(ise.get('max'))}. The worst:",
        "",
    ]
    rows = [
        [f"`{w.get('plant')}`", _ratio(w.get("ISE_ratio")), str(w.get("plant_is"))]
        for w in draw.get("worst") or []
    ]
    return [*lines, *table(("plant", "ISE ratio", "what it is"), rows, source), ""]


def routes_lines(summary: Mapping[str, Any], source: str) -> list[str]:
    """The routes' table, the family draw and the bars; nothing where the stage had none."""
    routes = summary.get("routes")
    if not isinstance(routes, Mapping):
        return []
    held = summary.get("held_out") or {}
    rows = [
        [f"`{name}`", *(policy_cell(e["policies"].get(k)) for k in ("card", "zero_shot"))]
        for name, e in held.items()
        if isinstance(e, Mapping)
    ]
    lines = [
        "Zero-shot (issue 50): the model card route, trained over a plant family and the 20 "
        "other catalogue plants, given each plant's model; the in-context route, the tag-free "
        "policy trained over those 20 plants, reading it from its window (its signals' scales "
        "from its demonstrations):",
        "",
        *table(_HEADER, rows, source),
        "",
    ]
    draw = summary.get("family_draw")
    if isinstance(draw, Mapping):
        lines += _draw_lines(draw, source)
    cells = [f"`{k}` {'pass' if v else '**fail**'}" for k, v in (routes.get("bars") or {}).items()]
    cells += [f"`{k}` **not run** (no bars)" for k in routes.get("not_run") or []]
    return [*lines, f"Issue 50's bars: {'; '.join(cells)}.", ""]


def _unseen(recipe: Recipe, data: Mapping[str, Any]) -> list[str]:
    lines = BASE_SECTIONS["unseen"](recipe, data)
    return lines + routes_lines(data["summary"], recipe.files["summary"])


#: The page's sections, the held-out one with the routes.
SECTIONS = {**BASE_SECTIONS, "unseen": _unseen}
