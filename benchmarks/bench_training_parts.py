"""Where a training's time goes besides its epochs: closed-loop validation and DAgger rounds.

    python benchmarks/bench_training_parts.py [--policy models/policy.ckpt] [--repeats 3]

With the trained default policy on all 25 plants, times (median of ``--repeats``):

* ``closed_loop_val``: one ``val/closed_loop`` score (``closed_loop_val`` of the config:
  steps of each amplitude from rest, every training plant), run after every validation, with
  LQI's responses kept from the first (``closed_loop_val_first``: that first one);
* ``dagger_round``: one DAgger round as the default config runs it (``dagger.sampler``'s
  rollouts, labelled by the experts: ``dagger.labeller``), at the last round's beta.

The epochs are the rest of the training's wall time (MLflow's ``time/epoch_s``). Figures are
printed and written to ``benchmarks/results/training_parts.json``.
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import torch
from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import load_policy
from generalist_control.plants.catalog import plants_from_config
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.training.labeller import ExpertLabeller
from generalist_control.training.sampler import RolloutSampler
from generalist_control.training.settings import read_training

RESULTS = Path(__file__).resolve().parent / "results"


def _median_time(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="models/policy.ckpt")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(1)
    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        cfg = compose("config")
    policy, meta = load_policy(args.policy)
    plants = [p for p in plants_from_config(as_dict(cfg.systems)) if p.name in meta["tags"]]
    runtime = PolicyRuntime(policy, meta)
    spec = cfg.closed_loop_val
    amps, duration = list(spec.amplitudes), float(spec.duration)

    def first() -> None:  # a new score: LQI's responses simulated too
        ClosedLoopScore(plants, amps, duration)(RuntimeAdapter(runtime))

    score = ClosedLoopScore(plants, amps, duration)  # as the training's callback keeps it
    with torch.inference_mode():
        t_first = _median_time(first, args.repeats)
        score(RuntimeAdapter(runtime))
        t_val = _median_time(lambda: score(RuntimeAdapter(runtime)), args.repeats)
    settings = read_training(as_dict(cfg))
    d = settings.dagger
    assert d is not None, "the default config runs DAgger"
    sampler = RolloutSampler(plants, d.sampler, settings.rollout_data, 0)
    labeller = ExpertLabeller(d.labeller, int(meta["history"]), int(meta["horizon"]),
                              policy.channels)  # fmt: skip
    bounds = {p.name: np.full(p.order, np.inf) for p in plants}
    beta = d.beta_at(d.rounds - 1)

    def one_round() -> None:
        with torch.inference_mode():
            labeller.label(sampler.run(d.rounds - 1, runtime, beta), bounds)

    t_dagger = _median_time(one_round, args.repeats)
    out = {
        "closed_loop_val_s": t_val,
        "closed_loop_val_first_s": t_first,
        "dagger_round_s": t_dagger,
        "plants": len(plants),
        "dagger_rollouts_per_plant": len(sampler.specs(0, plants[:1])[0][0]),
        "repeats": args.repeats,
    }
    print(
        f"closed-loop validation: {t_val:.2f} s per validation ({len(plants)} plants; "
        f"the first, with LQI's responses: {t_first:.2f} s)"
    )
    print(f"DAgger round: {t_dagger:.2f} s ({out['dagger_rollouts_per_plant']} rollouts/plant)")
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "training_parts.json").write_text(json.dumps(out, indent=2) + "\n")
    print(f"wrote {RESULTS / 'training_parts.json'}")


if __name__ == "__main__":
    main()
