"""How fast a plant family is drawn: plants drawn, LQI-designed and checked per second.

    python benchmarks/bench_families.py [--count 2000] [--repeats 3] [--data] [--out PATH]
                                        [overrides of conf/generate_families.yaml]

* ``draw``: :func:`~generalist_control.simulation.family_draw.draw_family` of ``--count``
  plants of the family (``families=default``), wall and CPU time, the median of
  ``--repeats`` (every repeat draws the same plants: the same seed); the candidates it took
  and the refusals per reason;
* ``parts``: one more draw taken apart: the candidates (the family's draws, realisations and
  weights), the LQI designs and pole checks, the batched settling check, and the settling
  check done one plant at a time with the simulator (``simulate``), which the batch replaces;
* ``--data``: the ``generate_families`` stage once (its demonstrations written to a
  temporary folder): wall time, trajectories, windows, MB on disk.

Machine facts and ``os.getloadavg()`` at the start and the end tell an idle run from a
loaded one. Printed, and written to ``benchmarks/results/families.json``.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # 5 x 5 matrices: one thread, as the stage
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import platform  # noqa: E402
import statistics  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from generalist_control.common.jsonsafe import write_json  # noqa: E402
from generalist_control.common.paths import conf_dir  # noqa: E402
from generalist_control.generate_families import run as generate_families  # noqa: E402
from generalist_control.simulation.family_draw import (  # noqa: E402
    Rejected,
    check_design,
    draw_family,
    read_families,
    settling_times,
)
from generalist_control.simulation.lqi import LQIController  # noqa: E402
from generalist_control.simulation.metrics import step_metrics  # noqa: E402
from generalist_control.simulation.simulate import simulate  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "families.json"
#: Plants the one-at-a-time settling check is timed on (then scaled to the draw's).
SIMULATE_SAMPLE = 100


def _timed(fn: Any, *args: Any) -> tuple[Any, float, float]:
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn(*args)
    return out, time.perf_counter() - wall, time.process_time() - cpu


def measure_draw(cfg: Any, count: int, repeats: int) -> dict[str, Any]:
    """Median wall and CPU seconds of drawing ``count`` plants, and the draw's counts."""
    family, settings = read_families(OmegaConf.to_container(cfg.families, resolve=True))
    runs = []
    for i in range(repeats):
        draw, wall, cpu = _timed(draw_family, family, count, settings.checks)
        runs.append({"wall_s": wall, "cpu_s": cpu, "loadavg": os.getloadavg()})
        print(f"draw {i + 1}: {count} plants in {wall:.2f} s (CPU {cpu:.2f} s)", flush=True)
    counts = draw.counts()
    wall = statistics.median(r["wall_s"] for r in runs)
    cpu = statistics.median(r["cpu_s"] for r in runs)
    return {
        "plants": count,
        "distinct_plants": len({d.plant.A.tobytes() + d.plant.C.tobytes() for d in draw.kept}),
        "counts": counts,
        "median_wall_s": wall,
        "median_cpu_s": cpu,
        "plants_per_s": count / wall,
        "ms_per_candidate_cpu": 1e3 * cpu / counts["candidates"],
        "runs": runs,
    }, (family, settings, counts["candidates"])


def measure_parts(family: Any, checks: Any, candidates: int) -> dict[str, Any]:
    """CPU seconds of each part of one draw, and of the settling check done plant by plant."""
    cands, _, t_draw = _timed(lambda: [family.candidate(i) for i in range(candidates)])
    t0 = time.process_time()
    designed = []
    for c in cands:
        if c.plant is not None:
            try:
                designed.append((c.plant, check_design(c.plant, checks.max_pole_dt)))
            except Rejected:
                pass
    t_design = time.process_time() - t0
    steps = round(checks.duration / family.dt)
    plants, gains = [p for p, _ in designed], [g for _, g in designed]
    _, _, t_batch = _timed(settling_times, plants, gains, steps)
    sample = designed[:SIMULATE_SAMPLE]
    t0 = time.process_time()
    for p, g in sample:
        tr = simulate(p, LQIController(p, g), np.ones((1, steps)))
        step_metrics(tr.t, tr.y, tr.u, tr.r[:, -1])
    t_each = (time.process_time() - t0) * len(designed) / max(len(sample), 1)
    return {
        "candidates": candidates,
        "designed": len(designed),
        "candidates_cpu_s": t_draw,
        "design_and_poles_cpu_s": t_design,
        "settling_batched_cpu_s": t_batch,
        "settling_one_by_one_cpu_s": t_each,
        "settling_one_by_one_from": len(sample),
    }


def measure_data(cfg: Any) -> dict[str, Any]:
    """The ``generate_families`` stage once, into a temporary folder."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "families"
        cfg = OmegaConf.merge(cfg, {"families": {"data_dir": str(out)}})
        manifest, wall, cpu = _timed(generate_families, cfg)
        sizes = {f.name: f.stat().st_size / 2**20 for f in out.iterdir() if f.is_file()}
    return {
        "wall_s": wall,
        "cpu_s": cpu,
        "plants": len(manifest["plants"]),
        "trajectories": manifest["n_trajectories"],
        "windows": manifest["n_demonstrations"],
        "mb": sizes,
        "mb_total": sum(sizes.values()),
    }


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    info = Path("/proc/cpuinfo")
    lines = info.read_text().splitlines() if info.is_file() else []
    names = [s.split(":", 1)[1].strip() for s in lines if s.startswith("model name")]
    return {
        "host": platform.node(),
        "cpu": names[0] if names else platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }


def report(result: dict[str, Any]) -> None:
    d = result["draw"]
    c = d["counts"]
    refused = ", ".join(f"{k} {v}" for k, v in c.items() if k not in ("candidates", "kept") and v)
    print(
        f"{d['plants']} plants ({d['distinct_plants']} distinct) from {c['candidates']} "
        f"candidates: median {d['median_wall_s']:.2f} s wall, {d['median_cpu_s']:.2f} s CPU "
        f"({d['plants_per_s']:.0f} plants/s; {d['ms_per_candidate_cpu']:.2f} ms CPU per "
        f"candidate); refused: {refused}"
    )
    p = result["parts"]
    print(
        f"parts (CPU s): candidates {p['candidates_cpu_s']:.2f}, designs "
        f"{p['design_and_poles_cpu_s']:.2f}, settling batched {p['settling_batched_cpu_s']:.2f} "
        f"vs one by one with simulate {p['settling_one_by_one_cpu_s']:.2f}"
    )
    if "data" in result:
        m = result["data"]
        print(
            f"data stage: {m['plants']} plants, {m['trajectories']} trajectories, "
            f"{m['windows']} windows, {m['mb_total']:.1f} MB in {m['wall_s']:.1f} s"
        )
    load = [" ".join(f"{v:.2f}" for v in result[k]) for k in ("loadavg_start", "loadavg_end")]
    print(f"load average: start {load[0]}, end {load[1]} ({result['machine']['cpu_count']} CPUs)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=2000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--data", action="store_true", help="also time the data stage once")
    ap.add_argument("--out", default=str(RESULTS))
    ap.add_argument("overrides", nargs="*")
    args = ap.parse_args()
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("generate_families", overrides=list(args.overrides))
    result: dict[str, Any] = {
        "benchmark": "plant family draw (conf/families/default.yaml)",
        "machine": machine(),
        "loadavg_start": os.getloadavg(),
        "overrides": args.overrides,
    }
    result["draw"], (family, settings, candidates) = measure_draw(cfg, args.count, args.repeats)
    result["parts"] = measure_parts(family, settings.checks, candidates)
    if args.data:
        result["data"] = measure_data(cfg)
    result["loadavg_end"] = os.getloadavg()
    report(result)
    write_json(args.out, result)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
