"""Write tests/durations.json, each test file's seconds, from ``pytest --durations=0`` output.

The suite's workers take whole files (``--dist loadfile``); tests/conftest.py hands them out
longest first from this table, so that no long file starts last while the other worker idles.
Usage: ``python -m pytest -q -n 2 --dist loadfile --no-loadscope-reorder --durations=0 | tee
out.txt``, then ``python scripts/test_durations.py out.txt``. A file the table lacks counts 0.
"""

from __future__ import annotations

import json
import re
import sys
from collections import Counter
from pathlib import Path

LINE = re.compile(r"\s*([\d.]+)s (?:call|setup|teardown)\s+(tests/[^:\s]+)::")
OUT = Path(__file__).resolve().parents[1] / "tests" / "durations.json"


def main(report: str, out: Path = OUT) -> None:
    """Sum the report's durations by file and write them to ``out``, longest first."""
    seconds: Counter[str] = Counter()
    for line in Path(report).read_text().splitlines():
        if m := LINE.match(line):
            seconds[m.group(2)] += float(m.group(1))
    if not seconds:
        sys.exit(f"{report} holds no durations: run pytest with --durations=0")
    table = {f: round(s, 1) for f, s in seconds.most_common()}
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(table, indent=1) + "\n")
    tmp.replace(out)
    print(f"{len(table)} files, {sum(table.values()):.0f} s in all -> {out}")


if __name__ == "__main__":
    main(sys.argv[1])
