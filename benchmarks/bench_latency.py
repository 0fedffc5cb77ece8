"""Benchmark the deployed policy's batch-1 ``step()`` latency on one CPU thread.

Run: ``python benchmarks/bench_latency.py [--policy models/policy.ckpt] [--steps 5000]
[--repeats 3] [--label "under load"] [--all-backends]``.

Each timed path steps one plant in its own closed loop with the plant (the plant's update is
not timed), after a warm-up; the paths are timed in interleaved blocks (10 rounds), so drift
of a shared machine's speed falls on all of them alike, and the whole measurement is
repeated (``--repeats``): the figures are the medians over the repeats of each repeat's
p50 and p99. The paths:

* ``lqi_step``: the LQI law's own step (:class:`LQIController`, batch 1), the yardstick;
* ``onnx_step``: :meth:`PolicyRuntime.step` with the ONNX backend, one plant (``reset(name)``):
  its per-sample path and the plant's own batch-1 graph, written from the weights
  (deploy/onnx_plant.py; issue 38);
* ``onnx_network_only``: that graph alone on the runtime's current window;
* ``onnx_general_step``: the same runtime with ``specialise=False``: the general path
  (dynamic-batch session, array bookkeeping), which is what ``onnx_step`` was before;
* with ``--all-backends`` also ``torch_step`` and ``torchscript_step``.

Prints p50 / p99 per path, the ratio of each p50 to the LQI step's and each plant period's
real-time factor (``p99 / dt``: the share of a sample period one step takes), checks that
``onnx_step`` gives the general path's controls (largest difference relative to the largest
control, over a closed loop of ``--steps`` samples), and writes
``benchmarks/results/latency.json``. Goal (issue 38): p50 at most 0.05 ms and at most 12x
the LQI step.

Without ``--policy`` an untrained policy of the default architecture (conf/model/
generalist.yaml: d = 32, M = 3, history 8, horizon 3, window scaling, error integral, linear
skip) is timed, its normaliser fitted on LQI step responses of the plant (``--normaliser
identity``: all scales one): latency does not depend on the weights.
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

from generalist_control.data.windows import build_windows, integral_of_error  # noqa: E402
from generalist_control.deploy.export import backend  # noqa: E402
from generalist_control.deploy.resolve import resolve  # noqa: E402
from generalist_control.deploy.runtime import PolicyRuntime, RejectedStep  # noqa: E402
from generalist_control.model.policy import Policy, load_policy  # noqa: E402
from generalist_control.plants.catalog import available_plants, load_plant  # noqa: E402
from generalist_control.plants.plant import pad_states  # noqa: E402
from generalist_control.simulation.lqi import LQIController  # noqa: E402
from generalist_control.simulation.simulate import discretise, simulate  # noqa: E402


#: The default recipe's network (conf/model/generalist.yaml, conf/data: history 8, horizon 3;
#: top-level experts 3), as training.setup.model_config builds it; other keys their defaults.
def _default_model() -> dict:
    """The default recipe's network config (conf/model/generalist.yaml, as training reads it)."""
    from hydra import compose, initialize_config_dir

    from generalist_control.common.paths import conf_dir
    from generalist_control.training.settings import model_config

    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        return model_config(compose("config"))


DEFAULT_MODEL = _default_model()
GOAL_MS, GOAL_RATIO = 0.05, 12.0


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
    block = max(1, steps // rounds)
    for _ in range(rounds):
        for loop in loops.values():
            loop.run(block)
    out = {}
    for name, loop in loops.items():
        a = np.asarray(loop.times, dtype=np.float64) / 1e6
        out[name] = {"p50_ms": float(np.percentile(a, 50)), "p99_ms": float(np.percentile(a, 99))}
    return out


def _fit_normaliser(policy: Policy, plant) -> None:
    """Fit the normaliser on windows of LQI step responses of ``plant`` (as training does)."""
    amps = np.array([-3.0, -1.0, 0.5, 2.0]) * plant.amplitude_scale
    tr = simulate(plant, LQIController(plant), np.repeat(amps[:, None], 120, axis=1))
    z = integral_of_error(tr.r, tr.y[:, :-1], plant.dt)
    n = len(amps)
    w = build_windows(pad_states(tr.x[:, :-1]), tr.r, tr.u, np.full(n, plant.tag),
                      np.full(n, plant.order), DEFAULT_MODEL["history"],
                      DEFAULT_MODEL["horizon"], z)  # fmt: skip
    arrays = (w.state, w.mask, w.ref, w.tag, w.target)
    policy.normaliser.fit(*(torch.from_numpy(np.ascontiguousarray(a)) for a in arrays))


def _policy(source: str | None, plant, normaliser: str):
    if source:
        return load_policy(resolve(source))
    torch.manual_seed(0)
    meta = {
        "tags": {plant.name: plant.tag},
        "orders": {plant.name: plant.order},
        "dt": plant.dt,
        "history": DEFAULT_MODEL["history"],
        "horizon": DEFAULT_MODEL["horizon"],
        "outputs": {plant.name: plant.C[0].tolist()},
    }
    policy = Policy(DEFAULT_MODEL)
    if normaliser == "fitted":
        _fit_normaliser(policy, plant)
    return policy.eval(), meta


def _loops(policy, meta, plant, all_backends: bool) -> dict[str, _Loop]:
    lqi = LQIController(plant)
    lqi.reset(1)
    loops = {"lqi_step": _Loop(lambda x, r: lqi.step(x[None, :], np.array([r]))[0], plant)}
    rt = PolicyRuntime(policy, meta, backend="onnx")
    rt.reset(plant.name)
    loops["onnx_step"] = _Loop(rt.step, plant, lambda: rt.reset(plant.name))
    state, mask, _, tag = rt.window()
    net = backend(policy, "onnx").single(int(tag[0]), mask)  # the plant's batch-1 graph

    def network_only(x, r):  # alone, on the runtime's current window
        state, _, ref, _ = rt.window()
        return net(state, ref)[0, 0]

    loops["onnx_network_only"] = _Loop(network_only, plant)
    general = PolicyRuntime(policy, meta, backend="onnx", specialise=False)
    general.reset(plant.name)
    loops["onnx_general_step"] = _Loop(general.step, plant, lambda: general.reset(plant.name))
    for name in ("torch", "torchscript") if all_backends else ():
        other = PolicyRuntime(policy, meta, backend=name)
        other.reset(plant.name)
        loops[f"{name}_step"] = _Loop(other.step, plant, lambda o=other: o.reset(plant.name))
    return loops


def agreement(policy, meta, plant, steps: int) -> dict[str, float]:
    """``onnx_step`` against the general path in one closed loop: largest differences.

    Both runtimes see the same states (the loop is closed through the general path's
    control); ``max_rel_u``: largest |u - u_general| over the largest |u_general|;
    ``max_rel_plan``: the same over every predicted control.
    """
    fast = PolicyRuntime(policy, meta, backend="onnx")
    ref = PolicyRuntime(policy, meta, backend="onnx", specialise=False)
    Ad, Bd = discretise(plant.A, plant.B, plant.dt)
    du = dp = top_u = top_p = 0.0
    x = np.zeros(plant.order)
    for rt in (fast, ref):
        rt.reset(plant.name)
    for k in range(steps):
        try:
            a, b = fast.step(x, _reference(k)), ref.step(x, _reference(k))
        except RejectedStep:
            x = np.zeros(plant.order)
            for rt in (fast, ref):
                rt.reset(plant.name)
            continue
        du, top_u = max(du, abs(a - b)), max(top_u, abs(b))
        dp = max(dp, float(np.abs(fast.plan - ref.plan).max()))
        top_p = max(top_p, float(np.abs(ref.plan).max()))
        x = Ad @ x + Bd[:, 0] * b
    return {"max_rel_u": du / max(top_u, 1e-300), "max_rel_plan": dp / max(top_p, 1e-300)}


def _summary(repeats: list[dict]) -> dict[str, dict[str, float]]:
    """Per path, the medians over the repeats of p50 and p99, and every repeat's values."""
    out = {}
    for name in repeats[0]:
        p50 = [r[name]["p50_ms"] for r in repeats]
        p99 = [r[name]["p99_ms"] for r in repeats]
        out[name] = {"p50_ms": float(np.median(p50)), "p99_ms": float(np.median(p99)),
                     "p50_ms_repeats": p50, "p99_ms_repeats": p99}  # fmt: skip
    return out


def _real_time(step_ms: dict[str, float]) -> dict[str, dict[str, float]]:
    """Per sample period of the catalogue: the plants, and the share of it a step takes."""
    periods: dict[float, list[str]] = {}
    for name in available_plants():
        periods.setdefault(float(load_plant(name).dt), []).append(name)
    return {
        f"{dt * 1e3:g} ms": {
            "plants": sorted(names),
            "p50_share": step_ms["p50_ms"] / (dt * 1e3),
            "p99_share": step_ms["p99_ms"] / (dt * 1e3),
        }  # fmt: skip
        for dt, names in sorted(periods.items())
    }


def _report(results, base, rt_factor, agree, args) -> bool:
    label = f" - {args.label}" if args.label else ""
    print(f"batch-1 step() latency on 1 thread, plant {args.plant} ({args.steps} steps x "
          f"{args.repeats} repeats, medians){label}")  # fmt: skip
    print(f"{'path':<22}{'p50 ms':>10}{'p99 ms':>10}{'p50 / LQI':>12}")
    for k, v in results.items():
        print(f"{k:<22}{v['p50_ms']:>10.4f}{v['p99_ms']:>10.4f}{v['p50_ms'] / base:>12.1f}")
    for period, v in rt_factor.items():
        print(f"real-time factor of onnx_step against a {period} period ({len(v['plants'])} "
              f"plants): p50 {v['p50_share']:.2e}, p99 {v['p99_share']:.2e}")  # fmt: skip
    print(f"onnx_step vs the general path: max rel. difference u {agree['max_rel_u']:.2e}, "
          f"plan {agree['max_rel_plan']:.2e}")  # fmt: skip
    p50 = results["onnx_step"]["p50_ms"]
    met = p50 <= GOAL_MS and p50 / base <= GOAL_RATIO
    print(f"goal p50 <= {GOAL_MS} ms and <= {GOAL_RATIO:g}x LQI: {'met' if met else 'NOT met'}")
    return met


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--policy", default=None, help="policy file or MLflow URI")
    ap.add_argument("--plant", default="two_mass_spring")
    ap.add_argument("--steps", type=int, default=5000)
    ap.add_argument("--warmup", type=int, default=500)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--label", default="", help='conditions, e.g. "under load" or "idle"')
    ap.add_argument("--all-backends", action="store_true", help="also torch and torchscript")
    ap.add_argument(
        "--normaliser",
        choices=["fitted", "identity"],
        default="fitted",
        help="untrained policy: normaliser fitted on LQI step responses, or all ones",
    )
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "latency.json"))
    args = ap.parse_args()
    torch.set_num_threads(1)
    plant = load_plant(args.plant)
    policy, meta = _policy(args.policy, plant, args.normaliser)
    loops = _loops(policy, meta, plant, args.all_backends)
    results = _summary([_interleaved(loops, args.steps, args.warmup) for _ in range(args.repeats)])
    base = results["lqi_step"]["p50_ms"]
    rt_factor = _real_time(results["onnx_step"])
    agree = agreement(policy, meta, plant, args.steps)
    met = _report(results, base, rt_factor, agree, args)
    payload = {
        "plant": plant.name,
        "policy": args.policy or f"untrained, default architecture, {args.normaliser} normaliser",
        "label": args.label, "steps": args.steps, "repeats": args.repeats,
        "threads": torch.get_num_threads(), "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(), "load_average": list(os.getloadavg()),
        "torch": torch.__version__, "results": results,
        "ratio_p50_to_lqi": {k: v["p50_ms"] / base for k, v in results.items()},
        "real_time_factor": rt_factor, "agreement_with_general_path": agree,
        "goal": {"p50_ms": GOAL_MS, "ratio_to_lqi": GOAL_RATIO, "met": met},
    }  # fmt: skip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(f".{out.name}.tmp")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    tmp.replace(out)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
