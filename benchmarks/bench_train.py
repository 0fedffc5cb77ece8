"""Training speed and memory of the Generalist Controller on CPU (and GPU, if present).

    python benchmarks/bench_train.py [--epochs 4] [--threads 1 2] [--data DIR] [overrides]

Without ``--data`` it builds a synthetic dataset with the data stage's own code: the six
plants of the catalogue that exist in every checkout (cstr, unstable, boeing747,
hydraulic_actuator, two_mass_spring, crazyflie_altitude) on the default amplitude grid and
duration of ``conf/data/demos.yaml`` (about 76k windows). It reports, at the default
d = 32, M = 3 and batch size:

* ``step``: samples/s of bare optimisation steps (forward, backward, clipping, AdamW) on
  batches from the in-memory loader, median over ``--repeats`` timed passes;
* ``epoch``: wall time of Lightning training epochs (with and without validation), the
  median over epochs after the first, and the samples/s they imply;
* the projected time of the default training (``trainer.max_epochs`` epochs) on the full
  25-plant dataset of ~317k windows, scaled from the measured samples/s;
* peak RSS of the process.

Figures are printed and written to ``benchmarks/results/train.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import sys
import tempfile
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict
from generalist_control.data.demos import write_demos
from generalist_control.data.generation import build_manifest, generate_demos
from generalist_control.model.network import count_parameters
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import design_lqi
from generalist_control.training.datamodule import DemoDataModule
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.settings import read_training

PLANTS = (
    "cstr",
    "unstable",
    "boeing747",
    "hydraulic_actuator",
    "two_mass_spring",
    "crazyflie_altitude",
)
FULL_WINDOWS = 25 * 64 * 198  # 25 plants x 64 amplitudes x 198 windows (default grid)
RESULTS = Path(__file__).resolve().parent / "results" / "train.json"


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def compose_cfg(overrides: list[str]):
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return compose("config", overrides=overrides)


def make_data(cfg, out: Path) -> Path:
    data = OmegaConf.to_container(cfg.data, resolve=True)
    plants = []
    for name in PLANTS:  # the catalogue is being extended: skip a plant that does not build
        try:
            plant = load_plant(name)
            design_lqi(plant)
        except Exception as exc:  # noqa: BLE001
            print(f"skipping plant {name}: {exc}")
            continue
        plants.append(plant)
    demos = generate_demos(plants, data, progress=False)
    systems = {"plants": {p.name: {} for p in plants}}  # the shape the data stage records
    manifest = build_manifest(plants, demos, data, {"systems": systems, "data": data})
    return write_demos(out / "demos", demos, manifest)


def build(cfg, dm: DemoDataModule) -> ImitationModule:
    settings = read_training(
        as_dict(cfg)
    )  # the training config's sections, as train.py reads them
    lit = ImitationModule(settings.model, settings.optimizer, settings.scheduler, dm.meta())
    lit.policy.normaliser.fit(**dm.train_set.tensors)
    return lit


def bench_steps(
    lit: ImitationModule, dm: DemoDataModule, device: str, repeats: int, steps: int
) -> dict:
    """Median samples/s of bare optimisation steps over ``repeats`` passes of ``steps``."""
    lit = lit.to(device).train()
    opt = lit.configure_optimizers()["optimizer"]
    batches = []
    for i, batch in enumerate(dm.train_dataloader()):
        if i == steps:
            break
        batches.append({k: v.to(device) for k, v in batch.items()})

    def one_pass() -> float:
        if device == "cuda":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        for b in batches:
            loss = lit.policy.errors(b)[0].mean()  # the imitation loss (not the identity's)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(lit.parameters(), 1.0)
            opt.step()
        if device == "cuda":
            torch.cuda.synchronize()
        return time.perf_counter() - t0

    one_pass()  # warm-up
    times = [one_pass() for _ in range(repeats)]
    n = sum(b["tag"].shape[0] for b in batches)
    return {"samples_per_s": n / statistics.median(times), "samples_per_pass": n, "pass_s": times}


class EpochTimer(L.Callback):
    def __init__(self) -> None:
        self.train_s: list[float] = []
        self.epoch_s: list[float] = []

    def on_train_epoch_start(self, trainer, pl_module) -> None:
        self._t0 = time.perf_counter()

    def on_validation_start(self, trainer, pl_module) -> None:
        if not trainer.sanity_checking:
            self.train_s.append(time.perf_counter() - self._t0)

    def on_train_epoch_end(self, trainer, pl_module) -> None:
        self.epoch_s.append(time.perf_counter() - self._t0)


def bench_epochs(cfg, dm: DemoDataModule, accelerator: str, epochs: int) -> dict:
    lit = build(cfg, dm)
    timer = EpochTimer()
    trainer = L.Trainer(
        accelerator=accelerator,
        devices=1,
        max_epochs=epochs,
        gradient_clip_val=1.0,
        logger=False,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        num_sanity_val_steps=0,
        callbacks=[timer],
    )
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*does not have many workers.*")
        trainer.fit(lit, datamodule=dm)
    timed_train = timer.train_s[1:] or timer.train_s
    timed_epoch = timer.epoch_s[1:] or timer.epoch_s
    return {
        "train_s": timer.train_s,
        "epoch_s": timer.epoch_s,
        "median_train_s": statistics.median(timed_train),
        "median_epoch_s": statistics.median(timed_epoch),
        "samples_per_s": len(dm.train_set) / statistics.median(timed_train),
        "epoch_samples_per_s": len(dm.train_set) / statistics.median(timed_epoch),
    }


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--epochs", type=int, default=4, help="Lightning epochs (first untimed)")
    p.add_argument("--repeats", type=int, default=5, help="timed passes of bare steps")
    p.add_argument("--steps", type=int, default=40, help="batches per timed pass")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="torch CPU threads")
    p.add_argument("--data", type=Path, default=None, help="a data/demos dir to use instead")
    p.add_argument("overrides", nargs="*", help="Hydra overrides, e.g. model.hidden=64")
    args = p.parse_args(argv)
    cfg = compose_cfg(args.overrides)
    L.seed_everything(int(cfg.seed), verbose=False)
    result: dict = {
        "command": "python benchmarks/bench_train.py " + " ".join(sys.argv[1:]),
        "torch": torch.__version__,
        "python": platform.python_version(),
        "cpu": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "hidden": int(cfg.model.hidden),
        "experts": int(cfg.experts),
        "batch_size": int(cfg.loader.batch_size),
        "max_epochs": int(cfg.trainer.max_epochs),
        "loadavg_start": os.getloadavg(),
    }
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        data_dir = args.data or make_data(cfg, Path(tmp))
        settings = read_training(as_dict(cfg))
        dm = DemoDataModule(
            data_dir,
            settings.history,
            settings.horizon,
            settings.loader,
            seed=settings.seed,
            channels=list(cfg.model.channels),
        )
        dm.setup("fit")
        result.update(
            data_prep_s=time.perf_counter() - t0,
            plants=sorted(dm.tags),
            n_train_windows=len(dm.train_set),
            n_val_windows=len(dm.val_set),
            n_parameters=count_parameters(build(cfg, dm)),
        )
        frac_train = len(dm.train_set) / (len(dm.train_set) + len(dm.val_set))
        for threads in args.threads:
            torch.set_num_threads(threads)
            step = bench_steps(build(cfg, dm), dm, "cpu", args.repeats, args.steps)
            epoch = bench_epochs(cfg, dm, "cpu", args.epochs)
            full_epoch_s = FULL_WINDOWS * frac_train / epoch["epoch_samples_per_s"]
            result[f"cpu_{threads}t"] = {
                "step": step,
                "epoch": epoch,
                "projected_full_epoch_s": full_epoch_s,
                "projected_full_training_min": full_epoch_s * cfg.trainer.max_epochs / 60,
            }
        if torch.cuda.is_available():
            result["gpu_name"] = torch.cuda.get_device_name()
            result["gpu_step"] = bench_steps(build(cfg, dm), dm, "cuda", args.repeats, args.steps)
            result["gpu_epoch"] = bench_epochs(cfg, dm, "gpu", args.epochs)
            result["gpu_peak_mem_mb"] = torch.cuda.max_memory_allocated() / 2**20
    result["full_dataset_windows"] = FULL_WINDOWS
    result["peak_rss_mb"] = peak_rss_mb()
    result["loadavg_end"] = os.getloadavg()

    print(
        f"d={result['hidden']} M={result['experts']} batch={result['batch_size']} "
        f"params={result['n_parameters']} train windows={result['n_train_windows']} "
        f"val={result['n_val_windows']} ({len(result['plants'])} plants)"
    )
    for threads in args.threads:
        r = result[f"cpu_{threads}t"]
        c, e = r["step"], r["epoch"]
        print(
            f"CPU {threads} thread(s): bare steps {c['samples_per_s']:8.0f} samples/s | "
            f"Lightning epoch {e['median_epoch_s']:6.2f} s, {e['samples_per_s']:6.0f} "
            f"samples/s (train part), {e['epoch_samples_per_s']:6.0f} with validation | "
            f"full data: {r['projected_full_epoch_s']:5.1f} s/epoch, "
            f"{r['projected_full_training_min']:5.1f} min for {result['max_epochs']} epochs"
        )
    if "gpu_step" in result:
        print(
            f"GPU ({result['gpu_name']}) bare steps: {result['gpu_step']['samples_per_s']:.0f}"
            f" samples/s; epoch {result['gpu_epoch']['median_epoch_s']:.2f} s; "
            f"peak GPU memory {result['gpu_peak_mem_mb']:.0f} MB"
        )
    print(
        f"peak RSS {result['peak_rss_mb']:.0f} MB; load average {result['loadavg_start']} -> "
        f"{result['loadavg_end']} (other work on the machine slows multi-thread runs)"
    )
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(result, indent=2) + "\n")
    print(f"wrote {RESULTS}")
    return result


if __name__ == "__main__":
    main()
