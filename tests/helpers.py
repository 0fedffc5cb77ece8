"""Shared test utilities: compose the real Hydra config with overrides."""

from __future__ import annotations

import copy
import os

from hydra import compose, initialize_config_dir

from generalist_control.common.paths import conf_dir
from generalist_control.common.sections import as_dict

#: Composed configs by (folder, its files and their times of change, config, the overrides
#: that choose configs): Hydra takes about 0.8 s a composition, a copy 0.03 s, and the suite
#: composes hundreds of times.
_COMPOSED: dict[tuple, object] = {}


def _files(folder: str) -> int:
    return hash(
        tuple(
            sorted(
                (os.path.join(d, f), os.stat(os.path.join(d, f)).st_mtime_ns)
                for d, _, fs in os.walk(folder)
                for f in fs
            )
        )
    )


def _sets_a_value(override, folder: str) -> bool:
    """Whether Hydra applies ``override`` to the composed config (not to the defaults list)."""
    if override.is_sweep_override() or override.is_hydra_override():
        return False
    group = os.path.isdir(os.path.join(folder, override.key_or_group))
    return isinstance(override.value(), dict) or not group


def compose_cfg(*overrides: str, config: str = "config"):
    """The project's primary config (or ``config``, e.g. ``adapt``) with ``overrides`` applied
    (a fresh copy each call; composed again whenever a file of the config folder changed).

    As Hydra's ``compose`` does, and with its messages: the overrides that choose configs
    compose the config (cached), then the value overrides are applied to a copy in order
    (``ConfigLoaderImpl._apply_overrides_to_config``, what ``compose`` itself calls).
    """
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.override_parser.overrides_parser import OverridesParser

    folder = str(conf_dir())
    parsed = OverridesParser.create().parse_overrides(list(overrides))
    values, choices = [], []
    for o in parsed:  # each override is Hydra's to apply to the config or to its defaults list
        (values if _sets_a_value(o, folder) else choices).append(o)
    lines = [o.input_line for o in choices]
    key = (folder, _files(folder), config, tuple(lines))
    if key not in _COMPOSED:
        with initialize_config_dir(folder, version_base="1.3"):
            _COMPOSED[key] = compose(config, overrides=lines)
    cfg = copy.deepcopy(_COMPOSED[key])
    ConfigLoaderImpl._apply_overrides_to_config(values, cfg)
    return cfg


def config_section(cls, key: str, **changes):
    """The settings dataclass ``cls`` read from the default config's section ``key``, with
    ``changes`` (the defaults live in conf/ only)."""
    import dataclasses

    from omegaconf import OmegaConf

    from generalist_control.common.sections import read_section

    node = OmegaConf.to_container(OmegaConf.select(compose_cfg(), key), resolve=True)
    return dataclasses.replace(read_section(cls, node, key), **changes)


def sweep_callback(**changes):
    """The Hydra callback ``hydra.callbacks.mlflow_sweep`` as configured, with ``changes``."""
    from hydra.utils import instantiate

    with initialize_config_dir(str(conf_dir()), version_base="1.3"):
        node = compose("config", return_hydra_config=True).hydra.callbacks.mlflow_sweep
    return instantiate(node, **changes)


#: The tiny data config: eight step amplitudes, 2 s (40 samples) per trajectory.
TINY_DATA = {
    "history": 8,
    "horizon": 3,
    "duration": 2.0,
    "amplitudes": {
        "limit": 20.0,
        "symmetric": True,
        "segments": [{"start": 1.0, "stop": 4.0, "step": 1.0}],
    },
}

#: Closed-loop scoring on the tiny dataset's plants, with short runs.
TINY_CLOSED_LOOP = ("closed_loop.systems=[cstr,hydraulic_actuator]", "closed_loop.duration=3.0")


def tiny_train_overrides(data_dir, out, uri: str, *extra: str) -> list[str]:
    """A short CPU training on the tiny data with every output under ``out``.

    One epoch, MLflow in ``uri`` with an experiment named after ``out`` (artifacts under
    ``out``), models and checkpoints in ``out/models`` and ``out/run``.
    """
    return [
        f"paths.data_dir={data_dir}",
        f"paths.models_dir={out / 'models'}",
        f"run_dir={out / 'run'}",
        f"logger.tracking_uri={uri}",
        f"logger.experiment_name={out.name}",
        f"logger.artifact_location={out / 'mlruns'}",
        "trainer.accelerator=cpu",
        "trainer.max_epochs=1",
        "trainer.enable_progress_bar=false",
        "trainer.enable_model_summary=false",
        "systems.include=[cstr,hydraulic_actuator]",
        *extra,
    ]


def quick_overrides(data_dir, out, uri: str, *extra: str) -> list[str]:
    """:func:`tiny_train_overrides` with the debug config and short closed-loop scoring.

    Models and checkpoints are left to the caller (sweeps and trials place their own).
    """
    keep = [
        o
        for o in tiny_train_overrides(data_dir, out, uri)
        if not o.startswith(("paths.models_dir", "run_dir"))
    ]
    return ["debug=fast", *keep, *TINY_CLOSED_LOOP, *extra]


def policy_meta(names, history: int = 8, horizon: int = 3) -> dict:
    """The meta a policy trained on the catalogue plants ``names`` carries (see training)."""
    from generalist_control.plants.catalog import load_plant

    plants = [load_plant(n) for n in names]
    return {
        "tags": {p.name: p.tag for p in plants},
        "orders": {p.name: p.order for p in plants},
        "dt": 0.05,
        "history": history,
        "horizon": horizon,
        "outputs": {p.name: p.C[0].tolist() for p in plants},
    }


def lqi_law_policy(names, gains_of, samples: int = 1, fit=None):
    """A real integrating policy whose skip path is the law ``-Kx x - Ki z``, and its meta.

    ``gains_of(plant)`` gives each plant's gains (e.g. ``design_lqi``). The experts' last
    layers are zero, so the output is the skip path alone; each plant's embedding row is a unit
    vector, so the skip's weights on it are that plant's gains on the newest sample in the
    normaliser's units (non-trivial scales, seeded), the same on every step of the horizon.
    ``samples``: how many of the newest samples the skip reads; ``fit``: windows (``state``,
    ``mask``, ``ref``, ``tag``, ``target`` tensors) to fit the normaliser on instead.
    """
    import numpy as np
    import torch

    from generalist_control.model.policy import Policy
    from generalist_control.plants.catalog import load_plant
    from generalist_control.plants.definition import MAX_ORDER

    torch.manual_seed(0)
    config = net_config(
        hidden=32, experts=2, window_scale=True, channels=["integral"], skip="linear",
        skip_samples=samples,
    )  # fmt: skip
    pol = Policy(config)
    g = torch.Generator().manual_seed(3)
    width, T, K = MAX_ORDER + 1, pol.history, pol.horizon
    n = samples
    with torch.no_grad():
        for expert in pol.net.experts:
            expert[-1].weight.zero_()
            expert[-1].bias.zero_()
        if fit is None:
            pol.normaliser.state_scale.uniform_(0.5, 3.0, generator=g)
            pol.normaliser.control_scale.uniform_(0.5, 3.0, generator=g)
        else:
            pol.normaliser.fit(**fit)
        rows = pol.net.plant.rows.weight
        rows.copy_(torch.eye(rows.shape[0], rows.shape[1]))
        gains_layer = pol.net.skip.gains
        gains_layer.weight.zero_()
        gains_layer.bias.zero_()
        for name in names:
            plant = load_plant(name)
            gains = gains_of(plant)
            sx = pol.normaliser.state_scale[plant.tag].double().numpy()
            su = float(pol.normaliser.control_scale[plant.tag])
            row = np.zeros(n * width + n)  # newest n samples: [x (padded), z] each, then r
            newest = (n - 1) * width
            row[newest : newest + plant.order] = -gains.Kx * sx[: plant.order] / su
            row[newest + MAX_ORDER] = -gains.Ki * sx[MAX_ORDER] / su
            gains_layer.weight[:, plant.tag] = torch.tensor(np.tile(row, K))
    return pol.eval(), policy_meta(list(names), T, K)


def net_config(
    hidden: int = 32,
    experts: int = 3,
    heads: int = 3,
    stride: int = 2,
    history: int = 8,
    horizon: int = 3,
    channels=(),
    window_scale: bool = False,
    skip=None,
    skip_samples: int = 1,
    plant: str = "tag",
    law_history=None,
    n_tags: int = 25,
    **plant_options,
) -> dict:
    """A network config (the shape of ``conf/model``) in plain types; the paper's by default.

    ``skip``: None, ``"linear"`` or ``"context"`` (``skip_samples`` each); ``plant``:
    ``"tag"`` or ``"inferred"`` (``plant_options``: ``noise``, ``loss_weight``, ``models`` --
    a dict of TransitionModels settings, or None).
    """
    base = "generalist_control.model."
    if plant == "tag":
        part = {"_target_": base + "plant.TagEmbedding", "_partial_": True, "n_tags": n_tags}
    else:
        models = plant_options.pop("models", {})
        identifier = {"_target_": base + "identifier.TransitionSet", "_partial_": True}
        if models is not None:
            identifier["models"] = {
                "_target_": base + "identifier.TransitionModels",
                "_partial_": True,
                **models,
            }
        part = {"_target_": base + "plant.InferredPlant", "_partial_": True, "n_tags": n_tags,
                "identifier": identifier, **plant_options}  # fmt: skip
    config = {
        "_target_": base + "network.GeneralistNetwork",
        "hidden": hidden, "heads": heads, "stride": stride, "experts": experts,
        "history": history, "horizon": horizon, "law_history": law_history,
        "channels": list(channels), "window_scale": window_scale, "plant": part,
    }  # fmt: skip
    if skip is not None:
        kind = {"linear": "LinearSkip", "context": "ContextSkip"}[skip]
        config["skip"] = {"_target_": base + f"linear.{kind}", "_partial_": True,
                          "samples": skip_samples}  # fmt: skip
    return config


def build_net(**kwargs):
    """The :class:`GeneralistNetwork` of :func:`net_config`."""
    from generalist_control.model.policy import build_network

    return build_network(net_config(**kwargs))


def train(cfg):
    """Train as ``python train.py`` does: the config read once, then the work."""
    from generalist_control.training.fit import train as fit
    from generalist_control.training.settings import read_training

    return fit(read_training(as_dict(cfg)))


#: What the fast adaptations add to ``conf/adapt.yaml``: a few steps on the tiny data recipe.
TINY_ADAPT = (
    "logger.log_model=false", "adapt.epochs=2", "adapt.rounds=1", "adapt.batch_size=64",
    "data.duration=2.0", "data.families=null",
    "data.amplitudes.segments=[{start:1.0,stop:4.0,step:1.0}]",
)  # fmt: skip


def untrained_policy(tmp, tiny_demos, name: str = "base.ckpt", **kind):
    """An untrained policy on cstr and hydraulic_actuator, its scales fitted, saved in ``tmp``.

    The default recipe's parts, or ``kind`` (``plant="inferred"``: the tag-free recipe's).
    """
    import torch

    from generalist_control.model.policy import Policy, save_policy

    torch.manual_seed(0)
    options = {"skip": "linear", "channels": ["integral"], **kind}
    if kind.get("plant") == "inferred":
        options.update(skip="context", channels=["integral", "previous_control"])
    config = net_config(hidden=16, experts=2, window_scale=True, **options)
    pol = Policy(config)
    w = tiny_demos.windows(8, 3, True, "previous_control" in config["channels"])
    fields = ("state", "mask", "ref", "tag", "target")
    pol.normaliser.fit(**{k: torch.from_numpy(getattr(w, k)) for k in fields})
    meta = policy_meta(["cstr", "hydraulic_actuator"])
    return save_policy(tmp / name, pol, meta)


def adapt_request(policy, run_dir, uri: str, plant: str = "mass_spring_damper", *extra: str):
    """The adapt command's settings as its entry point reads them: conf/adapt.yaml composed."""
    from pathlib import Path

    from omegaconf import OmegaConf

    from generalist_control.adaptation.request import read_request

    where = f"logger.artifact_location={Path(run_dir).parent / 'mlruns'}"  # a new experiment's
    cfg = compose_cfg(f"plant={plant}", f"policy={policy}", f"logger.tracking_uri={uri}", where,
                      *TINY_ADAPT, *extra, config="adapt")  # fmt: skip
    return read_request(OmegaConf.to_container(cfg, resolve=True), run_dir)


# --- the project's commands, run through a fork server (tests/zygote.py) ---

#: Set to run every command as a real process (the zygote's faithfulness, checked whole).
REAL_PROCESSES_ENV = "GC_TEST_REAL_PROCESSES"
_ZYGOTES: dict = {}  # the worker's fork servers by their start-up environment, started on use

#: Read once, as an interpreter or its libraries start (OpenMP's and BLAS's thread pools, hash
#: seeds, ...): a command whose environment sets them differently needs a server started so.
_AT_START = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")


def _start_env(env: dict[str, str]) -> tuple:
    """What of ``env`` a process reads as it starts (PYTHONPATH aside: sys.path is set later)."""
    return tuple(
        sorted(
            (k, v)
            for k, v in env.items()
            if k in _AT_START or (k.startswith("PYTHON") and k != "PYTHONPATH")
        )
    )


def _runs_in_zygote(cmd: list[str], cwd: str, env: dict[str, str]) -> bool:
    """Whether ``cmd`` is a project command the fork server runs as it is on disk."""
    import sys
    from pathlib import Path

    import generalist_control

    if os.environ.get(REAL_PROCESSES_ENV) or len(cmd) < 2 or cmd[0] != sys.executable:
        return False
    src = Path(generalist_control.__file__).resolve().parents[1]
    for entry in filter(None, env.get("PYTHONPATH", "").split(os.pathsep)):
        other = Path(entry).resolve()
        if other != src and (other / "generalist_control").exists():
            return False  # another copy of the package: only a fresh process imports it
    if cmd[1] == "-m":
        return len(cmd) > 2 and cmd[2].startswith("generalist_control.")
    script = Path(cwd, cmd[1]).resolve()
    return script.suffix == ".py" and src.parent in script.parents


def _zygote(env: dict[str, str]):
    """The fork server for ``env`` (started, its imports done), or None where it cannot fork."""
    import atexit
    import subprocess
    import sys
    from pathlib import Path

    key = _start_env(env)
    if key in _ZYGOTES and (_ZYGOTES[key] is None or _ZYGOTES[key].poll() is None):
        return _ZYGOTES[key]  # None: it could not fork here, real processes run instead
    start = {k: v for k, v in os.environ.items() if (k, v) not in _start_env(os.environ)}
    start.update(key)
    server = Path(__file__).with_name("zygote.py")
    proc = subprocess.Popen([sys.executable, str(server)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, env=start, bufsize=0)  # fmt: skip
    if not _answer(proc).get("ready"):
        proc.kill()
        proc.wait()
        _ZYGOTES[key] = None
        return None
    atexit.register(lambda: (proc.stdin.close(), proc.wait(timeout=30)))
    _ZYGOTES[key] = proc
    return proc


def _answer(server) -> dict:
    """The server's next line (read a byte at a time: nothing waits in a buffer of ours)."""
    import json

    line = b""
    while not line.endswith(b"\n"):
        byte = os.read(server.stdout.fileno(), 1)
        if not byte:
            return {}
        line += byte
    return json.loads(line)


def run_command(cmd, *, cwd, env=None, timeout=None, check=False):
    """``subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, ...)``.

    A project command (``python train.py``, ``python -m generalist_control.<x>``, a script
    of this repository, with this checkout's package) runs in a child of the fork server
    (tests/zygote.py): its own process, without the 3-7 s of imports; any other command, or
    every one with ``GC_TEST_REAL_PROCESSES=1``, as a real process.
    """
    import json
    import select
    import signal
    import subprocess
    import tempfile
    from pathlib import Path

    cmd, cwd = [str(c) for c in cmd], str(cwd)
    env = dict(os.environ if env is None else env)
    server = _zygote(env) if _runs_in_zygote(cmd, cwd, env) else None
    if server is None:
        return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True,
                              timeout=timeout, check=check)  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        out, err = Path(tmp, "stdout"), Path(tmp, "stderr")
        request = {"argv": cmd[1:], "cwd": cwd, "env": env, "stdout": str(out), "stderr": str(err)}
        server.stdin.write((json.dumps(request) + "\n").encode())
        pid = _answer(server)["pid"]
        ready, _, _ = select.select([server.stdout], [], [], timeout)
        if not ready:
            os.kill(pid, signal.SIGKILL)
        rc = _answer(server)["rc"]
        proc = subprocess.CompletedProcess(cmd, rc, out.read_text(), err.read_text())
    if not ready:
        raise subprocess.TimeoutExpired(cmd, timeout, proc.stdout, proc.stderr)
    if check:
        proc.check_returncode()
    return proc
