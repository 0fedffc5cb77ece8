"""What the user sees while training runs: the progress bar's metrics, readably printed."""

from __future__ import annotations

import math

import lightning as L
import pytest
from lightning.pytorch.callbacks import RichProgressBar
from lightning.pytorch.callbacks.progress.tqdm_progress import Tqdm
from omegaconf import OmegaConf

from generalist_control.common.sections import as_dict
from generalist_control.plants.catalog import load_plant
from generalist_control.simulation.comparison import ClosedLoopScore
from generalist_control.training.callbacks import ClosedLoopValidation
from generalist_control.training.datamodule import DemoDataModule
from generalist_control.training.lit_module import ImitationModule
from generalist_control.training.settings import LoaderSettings
from helpers import compose_cfg


def _shown(bar, value: float) -> str:
    """``value`` as the bar prints it (rich: the theme's format; tqdm: its format_num)."""
    if isinstance(bar, RichProgressBar):
        return f"{value:{bar.theme.metrics_format}}"
    return Tqdm.format_num(value)


def _readable(text: str, value: float) -> bool:
    """Three significant digits survive: the text reads back within 1% of the value."""
    return math.isclose(float(text), value, rel_tol=1e-2)


class _Losses(L.Callback):
    """Each training batch's loss and size, as the step returned it."""

    def __init__(self) -> None:
        self.seen: list[tuple[float, int]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        self.seen.append((float(outputs["loss"]), int(batch["tag"].shape[0])))


@pytest.fixture(scope="module")
def fitted(tiny_data_dir):
    """A tiny fit (two batches, one epoch) with Lightning's default progress bar."""
    cfg = compose_cfg("trainer.accelerator=cpu")
    loader = LoaderSettings(val_fraction=0.25, batch_size=64, val_batch_size=512)
    dm = DemoDataModule(tiny_data_dir, 8, 3, loader, channels=["integral"])
    dm.setup("fit")
    optimizer = OmegaConf.to_container(cfg.optimizer, resolve=True)
    lit = ImitationModule(model=as_dict(cfg)["model"], optimizer=optimizer, meta=dm.meta())
    plants = [load_plant("cstr"), load_plant("hydraulic_actuator")]
    trainer = L.Trainer(
        max_epochs=1,
        accelerator="cpu",
        logger=False,
        enable_checkpointing=False,
        enable_model_summary=False,
        enable_progress_bar=True,
        limit_train_batches=2,
        num_sanity_val_steps=0,
        callbacks=[ClosedLoopValidation(ClosedLoopScore(plants, duration=3.0)), _Losses()],
    )
    trainer.fit(lit, datamodule=dm)
    return trainer, lit


def test_the_bar_shows_the_monitored_closed_loop_score_and_the_losses(fitted):
    trainer, lit = fitted
    shown = trainer.progress_bar_callback.get_metrics(trainer, lit)
    assert {"val/closed_loop", "val/loss", "train/loss"} <= set(shown)
    assert not any(k.startswith("val/closed_loop/") for k in shown)  # per plant: logs only
    assert shown["val/closed_loop"] == pytest.approx(trainer.callback_metrics["val/closed_loop"])


def test_the_bar_prints_small_metrics_in_three_significant_digits(fitted):
    trainer, lit = fitted
    bar = trainer.progress_bar_callback
    for key, value in trainer.progress_bar_metrics.items():
        assert _readable(_shown(bar, value), value), (key, value, _shown(bar, value))
    # closed-loop errors of a good policy are 1e-9 .. 1e-12, a late loss 1e-4 .. 1e-6
    for value in (1.234e-12, 4.567e-5, 0.0123, 3.21):
        assert _readable(_shown(bar, value), value), _shown(bar, value)


def test_other_bars_keep_their_own_format(fitted):
    """The format is set on the training's bar only (rich shares one default theme)."""
    assert RichProgressBar().theme.metrics_format == ".3f"


def test_the_epoch_training_loss_is_the_mean_over_its_windows(fitted):
    trainer, _ = fitted
    seen = next(c for c in trainer.callbacks if isinstance(c, _Losses)).seen
    assert len(seen) == 2  # logged once, with the epoch's last batch, from the sums of both
    want = sum(loss * n for loss, n in seen) / sum(n for _, n in seen)
    assert float(trainer.callback_metrics["train/loss"]) == pytest.approx(want, rel=1e-6)
