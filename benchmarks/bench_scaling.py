"""How cost grows with the number of plants: the data stage, a training epoch, the evaluation.

    python benchmarks/bench_scaling.py [--plants 25 50 100] [--repeats 3] [--batches K]
                                       [--smoke] [--out PATH] [overrides]

For each count N of plants (each figure the median of ``--repeats`` runs):

* ``data``: :func:`~generalist_control.data.generation.generate_demos` on the default data
  config (``conf/data/demos.yaml``), wall time; and the windows its data yields;
* ``epoch``: one training epoch of the default network with ``model.plant.n_tags = N``:
  bare steps (forward, backward, clipping, AdamW; the batch's gather from the in-memory
  training windows included) on one CPU thread, and on the GPU
  beside it where CUDA is available. ``--batches K`` times K batches only and reports the
  epoch time their throughput implies (``epoch_s_kind`` says which);
* ``evaluation``: :func:`~generalist_control.evaluation.runner.evaluate` on the default
  scenarios and backend (``conf/evaluation/default.yaml``) of an untrained policy of the
  default architecture, its normaliser fitted on the training windows. GC runs that leave
  the policy's range are dropped from the batch (their share: ``gc_diverged``).

N = 25 is the catalogue; beyond it, variants of the catalogue plants (drawn, untimed, as
the data stage's ``data.variants`` are), dealt round-robin, each a plant of its own:
``<plant>_v<i>``, tags 25 .. N - 1. Scenarios that name their plants run on those only.
The growth exponent k (cost ~ N^k) is the least-squares slope of log cost against log N.
Machine facts and ``os.getloadavg()`` (start, each N, end) tell an idle run from a loaded
one. Printed, and written atomically to ``benchmarks/results/scaling.json``. ``--smoke``:
N = 2 and 4 (two catalogue plants, two variants), 2 s trajectories on eight amplitudes,
two 3 s scenarios, one repeat: a check that the script runs, not a measurement.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")  # one thread, as the data stage and training
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import dataclasses  # noqa: E402
import platform  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Sequence  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra import compose, initialize_config_dir  # noqa: E402
from omegaconf import OmegaConf  # noqa: E402

from generalist_control.common.jsonsafe import write_json  # noqa: E402
from generalist_control.common.paths import conf_dir  # noqa: E402
from generalist_control.common.sections import as_dict
from generalist_control.data.generation import amplitude_grid, generate_demos  # noqa: E402
from generalist_control.deploy.runtime import PolicyRuntime  # noqa: E402
from generalist_control.deploy.runtime_plants import integral_facts  # noqa: E402
from generalist_control.evaluation.runner import evaluate  # noqa: E402
from generalist_control.model.policy import Policy  # noqa: E402
from generalist_control.plants.catalog import check_tags, plants_from_config  # noqa: E402
from generalist_control.plants.definition import Plant  # noqa: E402
from generalist_control.simulation.variant_sampling import sample_variants  # noqa: E402
from generalist_control.training.datamodule import (  # noqa: E402
    BatchIndexSampler,
    WindowTensors,
    split_by_trajectory,
)
from generalist_control.training.lit_module import ImitationModule  # noqa: E402
from generalist_control.training.settings import TrainingSettings, read_training  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results" / "scaling.json"
WARMUP_BATCHES = 5
#: --smoke: catalogue plants kept, counts N, data overrides, scenarios kept and their length.
SMOKE_CATALOGUE, SMOKE_PLANTS = 2, [2, 4]
SMOKE_DATA = ["data.duration=2.0", "data.amplitudes.segments=[{start:1.0,stop:4.0,step:1.0}]"]
SMOKE_SCENARIOS, SMOKE_SCENARIO_S = ("step", "random_steps"), 3.0


def growth_exponent(counts: Sequence[float], costs: Sequence[float]) -> float | None:
    """``k`` of ``cost ~ N^k``: the least-squares slope of log cost against log N.

    None with fewer than two distinct counts or a cost that is not a positive number.

    >>> growth_exponent([1, 2, 4], [1, 4, 16])
    2.0
    """
    n, c = np.asarray(counts, dtype=float), np.asarray(costs, dtype=float)
    if len(np.unique(n)) < 2 or not (np.all(np.isfinite(c)) and np.all(c > 0)):
        return None
    return round(float(np.polyfit(np.log(n), np.log(c), 1)[0]), 12)


def compose_cfg(overrides: Sequence[str] = ()) -> Any:
    """The project's primary config with ``overrides``."""
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=list(overrides))


def plant_set(catalogue: Sequence[Plant], n: int, data: dict[str, Any]) -> list[Plant]:
    """``n`` distinct plants: the catalogue's first ``n``, or all of it and variants.

    The ``n - len(catalogue)`` variants are dealt round-robin over the catalogue plants (in
    tag order), drawn with ``data.variants``'s seed, range and max_tries and held to the
    largest steps of the amplitude grid (as the data stage's variants are), and renamed
    ``<plant>_v<i>`` with tags ``len(catalogue) ..  n - 1``.
    """
    if n <= len(catalogue):
        return list(catalogue[:n])
    base, extra, v = len(catalogue), n - len(catalogue), data["variants"]
    top = float(np.abs(amplitude_grid(data["amplitudes"])).max())
    steps = int(round(float(data["duration"]) / catalogue[0].dt))
    draws = [  # plant j gets the variants k = j, j + base, ... of k < extra
        sample_variants(p, count, v["seed"], v["range"], (top, -top), steps, v["max_tries"])
        for p, count in ((p, (extra - j + base - 1) // base) for j, p in enumerate(catalogue))
        if count > 0
    ]
    plants = list(catalogue)
    for k in range(extra):
        draw, i = draws[k % base], k // base
        name = f"{draw.nominal.name}_v{i + 1}"
        plants.append(dataclasses.replace(draw.kept[i].plant, name=name, tag=base + k))
    return plants


def plant_meta(plants: Sequence[Plant], history: int, horizon: int) -> dict[str, Any]:
    """The meta training gives a policy of ``plants`` (``tests/helpers.py`` policy_meta)."""
    return {
        "tags": {p.name: p.tag for p in plants},
        "orders": {p.name: p.order for p in plants},
        "dt": plants[0].dt,
        "history": history,
        "horizon": horizon,
        **integral_facts(plants=plants),
    }


@dataclasses.dataclass(frozen=True)
class Setup:
    """What the training and evaluation measurements of one plant count read."""

    cfg: Any
    settings: TrainingSettings
    plants: list[Plant]
    meta: dict[str, Any]
    train: WindowTensors


def measure_data(
    plants: Sequence[Plant], data: dict, settings: TrainingSettings, repeats: int
) -> tuple[dict, WindowTensors]:
    """The data stage's wall time and windows; the training windows of its data."""
    channels = settings.model.get("channels") or ()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        demos = generate_demos(plants, data, progress=False)
        times.append(time.perf_counter() - t0)
    t0 = time.perf_counter()
    w = demos.windows(
        settings.history, settings.horizon, "integral" in channels, "previous_control" in channels
    )
    windows_s = time.perf_counter() - t0
    is_val = split_by_trajectory(demos.plant, settings.loader.val_fraction, settings.seed)
    train = WindowTensors(w, ~is_val[w.traj])
    out = {
        "s": times,
        "median_s": statistics.median(times),
        "trajectories": len(demos.r),
        "windows": len(w),
        "train_windows": len(train),
        "windows_build_s": windows_s,
    }
    return out, train


def _pass(lit: ImitationModule, opt, data: dict, order: list, clip: float, device: str):
    """Wall time and samples of bare steps over the index batches ``order``."""
    sync = torch.cuda.synchronize if device == "cuda" else lambda: None
    sync()
    t0, samples = time.perf_counter(), 0
    for idx in order:
        idx = idx.to(device)
        batch = {k: v[idx] for k, v in data.items()}
        loss = lit.policy.errors(batch)[0].mean()  # the imitation loss of training_step
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(lit.parameters(), clip)
        opt.step()
        samples += int(idx.numel())
    sync()
    return time.perf_counter() - t0, samples


def measure_epoch(s: Setup, device: str, repeats: int, batches: int | None) -> dict:
    """One epoch of bare steps (or ``batches`` of it), median over ``repeats`` epochs."""
    settings, train, clip = s.settings, s.train, float(s.cfg.trainer.gradient_clip_val)
    torch.manual_seed(settings.seed)
    lit = ImitationModule(settings.model, settings.optimizer, settings.scheduler, s.meta)
    lit.policy.normaliser.fit(**train.tensors)
    lit = lit.to(device).train()
    opt = lit.configure_optimizers()["optimizer"]
    data = {k: v.to(device) for k, v in train.tensors.items()}
    sampler = BatchIndexSampler(len(train), settings.loader.batch_size, True, settings.seed)
    per_epoch = len(sampler)

    def batches_of(epoch: int, limit: int | None) -> list:
        sampler.set_epoch(epoch)
        return list(sampler)[:limit]

    _pass(lit, opt, data, batches_of(0, WARMUP_BATCHES), clip, device)
    runs = [
        _pass(lit, opt, data, batches_of(1 + i, batches), clip, device) for i in range(repeats)
    ]
    times = [t for t, _ in runs]
    rate = runs[0][1] / statistics.median(times)
    whole = batches is None or batches >= per_epoch
    return {
        "device": device,
        "threads": torch.get_num_threads() if device == "cpu" else None,
        "batch_size": settings.loader.batch_size,
        "batches_per_epoch": per_epoch,
        "timed_batches": per_epoch if whole else batches,
        "timed_samples": runs[0][1],
        "s": times,
        "samples_per_s": rate,
        "epoch_s": statistics.median(times) if whole else len(train) / rate,
        "epoch_s_kind": "measured: whole epoch"
        if whole
        else f"implied: training windows / samples_per_s over {batches} timed batches",
    }


def scenarios_of(cfg: Any, smoke: bool) -> dict[str, dict]:
    """The default evaluation's scenarios (with ``smoke``, two of them, 3 s each)."""
    scenarios = OmegaConf.to_container(cfg.evaluation.scenarios, resolve=True)
    assert isinstance(scenarios, dict)
    if smoke:
        scenarios = {k: {**scenarios[k], "duration": SMOKE_SCENARIO_S} for k in SMOKE_SCENARIOS}
    return scenarios


def measure_eval(s: Setup, scenarios: dict, repeats: int) -> dict:
    """The evaluation's wall time for an untrained policy, median over ``repeats``."""
    torch.manual_seed(s.settings.seed)
    policy = Policy(s.settings.model)
    policy.normaliser.fit(**s.train.tensors)
    backend = str(s.cfg.evaluation.backend)
    t0 = time.perf_counter()
    runtime = PolicyRuntime(policy, s.meta, backend=backend)
    build_s = time.perf_counter() - t0
    crazyflie: Any = OmegaConf.to_container(s.cfg.evaluation.crazyflie, resolve=True)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        df, _ = evaluate(runtime, s.plants, scenarios, crazyflie, progress=False)
        times.append(time.perf_counter() - t0)
    gc = df[(df.controller == "GC") & (df.metric == "diverged")]
    return {
        "backend": backend,
        "runtime_build_s": build_s,
        "s": times,
        "median_s": statistics.median(times),
        "scenarios": len(scenarios),
        "gc_runs": len(gc),
        "gc_diverged": float(gc.value.mean()) if len(gc) else None,
    }


def measure_count(catalogue: Sequence[Plant], n: int, args: argparse.Namespace) -> dict:
    """Every measurement for ``n`` plants."""
    cfg = compose_cfg([f"model.plant.n_tags={n}", *args.overrides])
    settings = read_training(as_dict(cfg))
    data = OmegaConf.to_container(cfg.data, resolve=True)
    assert isinstance(data, dict)
    t0 = time.perf_counter()
    plants = plant_set(catalogue, n, data)
    out: dict[str, Any] = {"plants": n, "variants": max(0, n - len(catalogue))}
    out.update(variants_draw_s=time.perf_counter() - t0, loadavg=os.getloadavg())
    check_tags(plants, n)
    meta = plant_meta(plants, settings.history, settings.horizon)
    print(f"N = {n}: data stage ...", flush=True)
    out["data"], train = measure_data(plants, data, settings, args.repeats)
    setup = Setup(cfg, settings, plants, meta, train)
    print(f"N = {n}: training epoch ({len(train)} windows) ...", flush=True)
    cpu = measure_epoch(setup, "cpu", args.repeats, args.batches)
    gpu: dict[str, Any] = {"available": False, "note": "no GPU"}
    if torch.cuda.is_available():
        gpu = measure_epoch(setup, "cuda", args.repeats, args.batches)
        gpu["name"] = torch.cuda.get_device_name()
    out["epoch"] = {"cpu": cpu, "gpu": gpu}
    print(f"N = {n}: evaluation ...", flush=True)
    out["evaluation"] = measure_eval(setup, scenarios_of(cfg, args.smoke), args.repeats)
    return out


def machine() -> dict[str, Any]:
    """What the figures were measured on."""
    info = Path("/proc/cpuinfo")
    lines = info.read_text().splitlines() if info.is_file() else []
    names = [s.split(":", 1)[1].strip() for s in lines if s.startswith("model name")]
    return {
        "host": platform.node(),
        "cpu": names[0] if names else platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "memory_gb": os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30,
        "python": platform.python_version(),
        "torch": torch.__version__,
        "numpy": np.__version__,
        "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
    }


def growth(counts: list[dict]) -> dict[str, float | None]:
    """The growth exponent of every cost over the measured counts."""
    n = [c["plants"] for c in counts]
    gpu = [c["epoch"]["gpu"].get("epoch_s", float("nan")) for c in counts]
    return {
        "data_s": growth_exponent(n, [c["data"]["median_s"] for c in counts]),
        "windows": growth_exponent(n, [c["data"]["windows"] for c in counts]),
        "epoch_cpu_s": growth_exponent(n, [c["epoch"]["cpu"]["epoch_s"] for c in counts]),
        "epoch_gpu_s": growth_exponent(n, gpu),
        "evaluation_s": growth_exponent(n, [c["evaluation"]["median_s"] for c in counts]),
    }


def show(result: dict) -> None:
    """Print the table of costs and their growth exponents."""
    print(
        f"{'N':>4} {'data s':>8} {'windows':>9} {'epoch CPU s':>12} {'samples/s':>10} "
        f"{'epoch GPU s':>12} {'eval s':>8} {'GC diverged':>11}"
    )
    for c in result["counts"]:
        cpu, gpu, ev = c["epoch"]["cpu"], c["epoch"]["gpu"], c["evaluation"]
        g = f"{gpu['epoch_s']:12.2f}" if "epoch_s" in gpu else f"{'no GPU':>12}"
        print(
            f"{c['plants']:4d} {c['data']['median_s']:8.2f} {c['data']['windows']:9d} "
            f"{cpu['epoch_s']:12.2f} {cpu['samples_per_s']:10.0f} {g} {ev['median_s']:8.2f} "
            f"{ev['gc_diverged'] or 0:11.2f}"
        )
    k = ", ".join(
        f"{key} {'-' if v is None else f'{v:.2f}'}" for key, v in result["growth"].items()
    )
    print(f"growth exponent k (cost ~ N^k): {k}")
    print(f"epoch times: {result['counts'][0]['epoch']['cpu']['epoch_s_kind']}")
    load = [" ".join(f"{v:.2f}" for v in result[k]) for k in ("loadavg_start", "loadavg_end")]
    print(
        f"load average (1, 5, 15 min) {load[0]} -> {load[1]} on "
        f"{result['machine']['cpu_count']} CPUs; peak RSS {result['peak_rss_mb']:.0f} MB"
    )


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--plants", type=int, nargs="+", default=[25, 50, 100], help="counts N")
    p.add_argument("--repeats", type=int, default=3, help="runs per figure (median)")
    p.add_argument("--batches", type=int, default=None, help="time K batches, not the epoch")
    p.add_argument("--smoke", action="store_true", help="a tiny run that checks the script")
    p.add_argument("--out", type=Path, default=RESULTS, help="the JSON file written")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. data.duration=5")
    args = p.parse_args(argv)
    if args.smoke:
        args.plants, args.repeats = SMOKE_PLANTS, 1
        args.overrides = [*SMOKE_DATA, *args.overrides]
    return args


def main(argv: list[str] | None = None) -> dict:
    args = parse(argv)
    torch.set_num_threads(1)
    # the ONNX export of the LSTMs at a dynamic batch (the runtime's batch session) warns
    warnings.filterwarnings("ignore", message=".*batch_size other than 1.*")
    result: dict[str, Any] = {
        "benchmark": "scaling: data stage, training epoch, evaluation against plant count",
        "command": "python benchmarks/bench_scaling.py " + " ".join(argv or sys.argv[1:]),
        "smoke": args.smoke,
        "overrides": args.overrides,
        "batches": args.batches,
        "machine": machine(),
        "loadavg_start": os.getloadavg(),
        "repeats": args.repeats,
    }
    catalogue = plants_from_config(as_dict(compose_cfg(args.overrides).systems))
    if args.smoke:
        catalogue = catalogue[:SMOKE_CATALOGUE]
    result["catalogue"] = len(catalogue)
    result["counts"] = [measure_count(catalogue, n, args) for n in sorted(set(args.plants))]
    result["growth"] = growth(result["counts"])
    result["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    result["loadavg_end"] = os.getloadavg()
    show(result)
    write_json(args.out, result)
    print(f"wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
