"""A short training imitates the expert, and ``policy.ckpt`` is its best checkpoint.

Guards the loss itself (e.g. a flipped target sign, which makes the policy learn ``-u``):
the imitation error is measured here, in plant units, between the saved policy's controls
and the expert's controls read from the reloaded dataset, not through the module's loss.
"""

from __future__ import annotations

import os

import mlflow
import numpy as np
import pytest
import torch

from generalist_control.common.sections import as_dict
from generalist_control.data.demos import load_demos
from generalist_control.deploy.adapter import RuntimeAdapter
from generalist_control.deploy.runtime import PolicyRuntime
from generalist_control.model.policy import Policy, load_policy
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.lqi import LQIController
from generalist_control.simulation.simulate import Run, simulate, simulate_many
from helpers import compose_cfg, tiny_train_overrides, train

EPOCHS = 5
#: The default recipe (integral, no per-plant head, closed-loop validation as the monitor),
#: without DAgger or the post-training closed-loop scores, with short closed-loop validation
#: runs, small batches (~10 steps per epoch) and a constant, large learning rate, so that the
#: monitored val/closed_loop is not lowest at the last epoch (the test checks it is not): the
#: best checkpoint and the last one can be told apart.
EXTRA = (
    "logger.log_model=false",
    "dagger=null",
    "closed_loop.systems=[]",
    "closed_loop_val.duration=2.0",
    "loader.batch_size=64",
    "optimizer.lr=3e-3",  # a constant, large step: the score is not monotone
    "scheduler=null",
    f"trainer.max_epochs={EPOCHS}",
)


def _expert_targets(demos, horizon: int) -> np.ndarray:
    """The expert's next ``horizon`` controls at every window start, trajectory by trajectory."""
    B, N = demos.u.shape
    return np.stack(
        [demos.u[b, k : k + horizon] for b in range(B) for k in range(N - horizon + 1)]
    )


def _relative_mse(u: np.ndarray, target: np.ndarray, tags: np.ndarray) -> dict[int, float]:
    """Per tag: mean squared control error over the mean squared expert control."""
    return {
        int(t): float(np.mean((u[tags == t] - target[tags == t]) ** 2))
        / float(np.mean(target[tags == t] ** 2))
        for t in np.unique(tags)
    }


def _closed_loop_score_by_hand(policy: Policy, meta: dict, cfg) -> float:
    """``val/closed_loop`` as conf/config.yaml documents it, recomputed here.

    Per plant: steps of each ``closed_loop_val.amplitudes`` (times the amplitude scale) from
    rest, ``mean((y_GC - y_LQI)**2) / mean(y_LQI**2)`` per step, averaged over the steps and
    capped at 1; then the mean over the plants.
    """
    amps = np.asarray(list(cfg.closed_loop_val.amplitudes), dtype=float)
    plants = [load_plant(n) for n in sorted(meta["tags"])]
    steps = round(float(cfg.closed_loop_val.duration) / plants[0].dt)
    refs = [np.repeat(amps[:, None] * p.amplitude_scale, steps, axis=1) for p in plants]
    runs = [Run(p, r) for p, r in zip(plants, refs, strict=True)]
    with torch.no_grad():
        gc = simulate_many(runs, RuntimeAdapter(PolicyRuntime(policy, meta)))
    per_plant = []
    for p, r, tr in zip(plants, refs, gc, strict=True):
        assert not tr.diverged.any()
        y_lqi = simulate(p, LQIController(p), r).y
        err = np.mean((tr.y - y_lqi) ** 2, axis=1) / np.mean(y_lqi**2, axis=1)
        per_plant.append(min(1.0, float(err.mean())))
    return float(np.mean(per_plant))


def _state_dict(policy: Policy) -> dict[str, torch.Tensor]:
    return {k: v.detach().clone() for k, v in policy.state_dict().items()}


@pytest.mark.slow
def test_short_training_imitates_the_expert_and_saves_the_best_checkpoint(
    tiny_data_dir, tmp_path, mlflow_uri
):
    cfg = compose_cfg(*tiny_train_overrides(tiny_data_dir, tmp_path, mlflow_uri, *EXTRA))
    assert cfg.monitor == "val/closed_loop" and "integral" in cfg.model.channels
    assert "table" not in cfg.model
    mlflow.set_tracking_uri(mlflow_uri)
    another = mlflow.set_experiment(f"{tmp_path.name}-another")  # set earlier: no matter
    _, objs = train(cfg)
    assert os.environ["MLFLOW_EXPERIMENT_ID"] == another.experiment_id  # and kept

    # --- imitation, measured independently of the module's loss ---------------------------
    demos, _ = load_demos(tiny_data_dir)
    horizon = int(cfg.data.horizon)
    windows = demos.windows(int(cfg.data.history), horizon, integral=True)
    target = _expert_targets(demos, horizon)
    np.testing.assert_array_equal(windows.target, target.astype(np.float32))
    trained, meta = load_policy(tmp_path / "models" / "policy.ckpt")
    u_trained, _ = trained.predict_windows(windows)
    torch.manual_seed(int(cfg.seed))
    untrained = Policy(as_dict(cfg)["model"])  # the same network untrained, same normaliser
    untrained.normaliser.fit(**objs["datamodule"].train_set.tensors)
    u_untrained, _ = untrained.predict_windows(windows)
    err_trained = _relative_mse(u_trained, target, windows.tag)
    err_untrained = _relative_mse(u_untrained, target, windows.tag)
    assert set(err_trained) == {load_plant(n).tag for n in ("cstr", "hydraulic_actuator")}
    for tag in err_trained:
        # measured: about 0.016 of the expert's power after training, above 1 before
        assert err_untrained[tag] > 0.5, (tag, err_untrained)
        assert err_trained[tag] < 0.1 * err_untrained[tag], (tag, err_trained, err_untrained)
        assert err_trained[tag] < 0.1, (tag, err_trained)  # well below predicting zero (1.0)

    # --- policy.ckpt is the best checkpoint --------------------------------------------------
    ckpt_cb = objs["trainer"].checkpoint_callback
    assert ckpt_cb.monitor == "val/closed_loop" and ckpt_cb.mode == "min"
    best_path = ckpt_cb.best_model_path
    assert best_path and objs["best_checkpoint"] == best_path
    history = mlflow.MlflowClient().get_metric_history(objs["run_id"], "val/closed_loop")
    logged = {h.step: h.value for h in history}
    assert sorted(logged) == list(range(EPOCHS))
    best_epoch = min(logged, key=logged.get)
    assert best_epoch != EPOCHS - 1, logged  # so that best and last can be told apart
    assert best_path.endswith(f"best-epoch{best_epoch:03d}.ckpt")
    assert torch.load(best_path, weights_only=True)["epoch"] == best_epoch
    assert float(ckpt_cb.best_model_score) == pytest.approx(logged[best_epoch], rel=1e-6)
    from_best, _ = load_policy(best_path)
    saved, from_best = _state_dict(trained), _state_dict(from_best)
    assert saved.keys() == from_best.keys()
    for key in saved:
        torch.testing.assert_close(saved[key], from_best[key], rtol=0, atol=0, msg=key)
    # and the saved policy is the epoch whose logged score is the minimum: its closed-loop
    # score, recomputed here, is that value and no other epoch's
    score = _closed_loop_score_by_hand(trained, meta, cfg)
    assert score == pytest.approx(logged[best_epoch], rel=1e-5), (score, logged)
    others = [v for e, v in logged.items() if e != best_epoch]
    assert all(abs(v - score) > 1e-3 * score for v in others), (score, logged)
