"""Print several evaluations side by side (markdown): every scenario, then every plant.

Run: ``python scripts/compare_recipes.py paper=<dir>/metrics.csv ours=reports/eval/metrics.csv``
(each argument ``label=path`` of a ``metrics.csv`` written by
``python -m generalist_control.evaluate``).
"""

from __future__ import annotations

import sys

import pandas as pd

from generalist_control.evaluation.result_tables import recipes_markdown, scenarios_markdown


def main(argv: list[str]) -> None:
    if not argv or any("=" not in a for a in argv):
        raise SystemExit(__doc__)
    results = {}
    for arg in argv:
        label, _, path = arg.partition("=")
        results[label] = pd.read_csv(path)
    print(scenarios_markdown(results))
    print(recipes_markdown(results), end="")


if __name__ == "__main__":
    main(sys.argv[1:])
