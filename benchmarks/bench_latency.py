"""Benchmark the deployed policy's batch-1 ``step()`` latency on one CPU thread.

Run: ``python benchmarks/bench_latency.py [--policy models/policy.ckpt] [--steps 5000]
[--repeats 3] [--label "under load"] [--all-backends]``.

Each path steps one plant in its own closed loop with the plant (the plant's update is not
timed), after a warm-up; the paths are timed in interleaved blocks, so drift of a shared
machine's speed falls on all of them alike, and the figures are the medians over
``--repeats`` of each repeat's p50 and p99. The paths: ``lqi_step``, the LQI law's step (the
yardstick); ``onnx_step``, :meth:`PolicyRuntime.step` with the ONNX backend for one plant
reset by name; ``onnx_batch_step``, the same plant as a batch of one (the general path);
with ``--all-backends`` also ``torch_step``. Prints p50, p99 and
the ratio of each p50 to the LQI step's, checks that ``onnx_step`` gives the general path's
controls, and writes ``benchmarks/results/latency.json``. Goal (issue 49): p50 at most
0.06 ms, idle. Without ``--policy`` an untrained policy of the default architecture is timed
(latency does not depend on the weights), its normaliser fitted on LQI step responses.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402

from generalist_control.common.sections import as_dict
from generalist_control.data.windows import build_windows, integral_of_error  # noqa: E402
from generalist_control.deploy.policy_source import resolve  # noqa: E402
from generalist_control.deploy.runtime import PolicyRuntime, RejectedStep  # noqa: E402
from generalist_control.model.policy import Policy, load_policy  # noqa: E402
from generalist_control.plants.catalog import load_plant  # noqa: E402
from generalist_control.plants.definition import MAX_ORDER, pad_states  # noqa: E402
from generalist_control.simulation.lqi import LQIController  # noqa: E402
from generalist_control.simulation.simulate import discretise, simulate  # noqa: E402

GOAL_MS = 0.06


def _default_model() -> dict:
    """The default recipe's network config (conf/model/generalist.yaml, as training reads it)."""
    from hydra import compose, initialize_config_dir

    from generalist_control.common.paths import conf_dir

    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return as_dict(compose("config"))["model"]


def _reference(k: int) -> float:
    return 1.0 if (k // 200) % 2 == 0 else -1.0


class _Loop:
    """One timed path in its own closed loop with the plant (the plant update is not timed)."""

    def __init__(self, step, plant, reset=None) -> None:
        self.step, self.k, self.reset = step, 0, reset
        self.Ad, self.Bd = discretise(plant.A, plant.B, plant.dt)
        self.x = np.zeros(plant.order)
        self.times: list[int] = []

    def run(self, n: int, record: bool = True) -> None:
        for _ in range(n):
            r = _reference(self.k)
            t0 = time.perf_counter_ns()
            try:
                u = self.step(self.x, r)
            except RejectedStep:  # the loop left the policy's range (an untrained policy)
                self.x = np.zeros(self.x.shape)
                if self.reset is not None:
                    self.reset()
                continue
            t1 = time.perf_counter_ns()
            if record:
                self.times.append(t1 - t0)
            self.k += 1
            self.x = self.Ad @ self.x + self.Bd[:, 0] * float(u)
            if not np.all(np.isfinite(self.x)) or np.abs(self.x).max() > 1e6:
                self.x = np.zeros(self.x.shape)


def _interleaved(loops: dict[str, _Loop], steps: int, warmup: int, rounds: int = 10):
    """p50 and p99 (ms) of every path, timed in round-robin blocks (module docstring)."""
    for loop in loops.values():
        loop.times = []
        loop.run(warmup, record=False)
    for _ in range(rounds):
        for loop in loops.values():
            loop.run(max(1, steps // rounds))
    return {
        name: {f"p{q}_ms": float(np.percentile(np.asarray(loop.times) / 1e6, q)) for q in (50, 99)}
        for name, loop in loops.items()
    }


def _policy(source: str | None, plant):
    if source:
        return load_policy(resolve(source))
    torch.manual_seed(0)
    model = _default_model()
    meta = {"tags": {plant.name: plant.tag}, "orders": {plant.name: plant.order},
            "dt": plant.dt, "history": model["history"], "horizon": model["horizon"],
            "outputs": {plant.name: plant.C[0].tolist()}}  # fmt: skip
    policy = Policy(model)
    # the normaliser fitted on windows of LQI step responses, as training does
    amps = np.array([-3.0, -1.0, 0.5, 2.0]) * plant.amplitude_scale
    tr = simulate(plant, LQIController(plant), np.repeat(amps[:, None], 120, axis=1))
    z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt)
    n = len(amps)
    w = build_windows(pad_states(tr.x[:, :-1]), tr.r, tr.u, np.full(n, plant.tag),
                      np.full(n, plant.order), model["history"], model["horizon"], z)  # fmt: skip
    arrays = (w.state, w.mask, w.ref, w.tag, w.target)
    policy.normaliser.fit(*(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays))
    return policy.eval(), meta


def _batch_of_one(rt: PolicyRuntime, name: str):
    """``step(x, r)`` of ``rt`` reset to ``[name]``: the general path, padded state."""
    padded, ref = np.zeros((1, MAX_ORDER)), np.zeros(1)

    def step(x, r):
        padded[0, : len(x)], ref[0] = x, r
        return rt.step(padded, ref)[0]

    return step


def _loops(policy, meta, plant, all_backends: bool) -> dict[str, _Loop]:
    lqi = LQIController(plant)
    lqi.reset(1)
    loops = {"lqi_step": _Loop(lambda x, r: lqi.step(x[None, :], np.array([r]))[0], plant)}
    for name in ("onnx", "torch") if all_backends else ("onnx",):
        rt = PolicyRuntime(policy, meta, backend=name)
        rt.reset(plant.name)
        loops[f"{name}_step"] = _Loop(rt.step, plant, lambda rt=rt: rt.reset(plant.name))
    batch = PolicyRuntime(policy, meta, backend="onnx")
    batch.reset([plant.name])
    reset = lambda: batch.reset([plant.name])  # noqa: E731
    loops["onnx_batch_step"] = _Loop(_batch_of_one(batch, plant.name), plant, reset)
    return loops


def agreement(policy, meta, plant, steps: int) -> float:
    """Largest ``|u - u_general| / max |u_general|`` of ``onnx_step`` in one closed loop.

    Both runtimes see the same states (the loop is closed through the general path's).
    """
    fast, general = (PolicyRuntime(policy, meta, backend="onnx") for _ in range(2))
    batch = _batch_of_one(general, plant.name)
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    du = top = 0.0
    x = np.zeros(plant.order)
    fast.reset(plant.name)
    general.reset([plant.name])
    for k in range(steps):
        try:
            a, b = fast.step(x, _reference(k)), batch(x, _reference(k))
        except RejectedStep:
            x = np.zeros(plant.order)
            fast.reset(plant.name)
            general.reset([plant.name])
            continue
        du, top = max(du, abs(a - b)), max(top, abs(b))
        x = Ad @ x + Bd[:, 0] * b
    return du / max(top, 1e-300)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--policy", default=None, help="policy file or MLflow URI")
    ap.add_argument("--plant", default="two_mass_spring")
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--label", default="", help='conditions, e.g. "under load" or "idle"')
    ap.add_argument("--all-backends", action="store_true", help="also the torch backend")
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "latency.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    plant = load_plant(args.plant)
    policy, meta = _policy(args.policy, plant)
    loops = _loops(policy, meta, plant, args.all_backends)
    repeats = [_interleaved(loops, args.steps, args.warmup) for _ in range(args.repeats)]
    results = {
        name: {key: float(np.median([r[name][key] for r in repeats])) for key in repeats[0][name]}
        for name in loops
    }
    base = results["lqi_step"]["p50_ms"]
    ratio = {k: v["p50_ms"] / base for k, v in results.items()}
    agree = agreement(policy, meta, plant, args.steps)
    print(f"batch-1 step() on 1 thread, plant {args.plant}, {args.steps} steps x {args.repeats} "
          f"repeats, medians{f' - {args.label}' if args.label else ''}")  # fmt: skip
    print(f"{'path':<18}{'p50 ms':>10}{'p99 ms':>10}{'p50 / LQI':>12}")
    for k, v in results.items():
        print(f"{k:<18}{v['p50_ms']:>10.4f}{v['p99_ms']:>10.4f}{ratio[k]:>12.1f}")
    print(f"onnx_step against the general path: largest relative difference of u {agree:.2e}")
    met = results["onnx_step"]["p50_ms"] <= GOAL_MS
    print(f"goal onnx_step p50 <= {GOAL_MS} ms: {'met' if met else 'NOT met'}")
    payload = {
        "plant": plant.name, "label": args.label, "steps": args.steps, "repeats": args.repeats,
        "policy": args.policy or "untrained, default architecture, fitted normaliser",
        "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()), "torch": torch.__version__,
        "results": results, "ratio_p50_to_lqi": ratio, "max_rel_difference_u": agree,
        "goal": {"p50_ms": GOAL_MS, "met": met},
    }  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    tmp.replace(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
