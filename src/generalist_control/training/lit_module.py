"""Lightning training of a :class:`~generalist_control.model.policy.Policy` by behaviour cloning.

The loss is the MSE between the network's ``horizon`` controls and the LQI expert's, in the
policy's per-tag normalised units, so every plant weighs alike whatever its scale.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import lightning as L
import torch
from hydra.utils import instantiate
from lightning.pytorch.callbacks import RichProgressBar
from torch import Tensor

from generalist_control.model.policy import Policy

__all__ = ["ImitationModule"]


class ImitationModule(L.LightningModule):
    """Behaviour cloning of the LQI experts (plain-dict arguments: ``weights_only`` checkpoints).

    ``model`` is the network's config, ``optimizer`` and ``scheduler`` Hydra partials, ``meta``
    the data's facts. A plant part's own loss is added (``train/identity``).
    """

    def __init__(
        self,
        model: dict[str, Any],
        optimizer: dict[str, Any],
        scheduler: dict[str, Any] | None = None,
        meta: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        # in checkpoints only: the run's params are logger.params, not the hparams
        self.save_hyperparameters(logger=False)
        self.policy = Policy(model)
        self._val_hits: Tensor | None = None  #: an identity head's right guesses
        tags = (meta or {}).get("tags", {})
        self.tag_names = {int(t): str(name) for name, t in tags.items()}
        n_tags = self.policy.net.n_tags
        self._val_sse = torch.zeros(n_tags, dtype=torch.float64)
        self._val_count = torch.zeros(n_tags, dtype=torch.float64)
        self._train_sum, self._train_count = torch.zeros((), dtype=torch.float64), 0

    def on_train_epoch_start(self) -> None:
        """Reset the epoch's loss sums."""
        self._train_sum = torch.zeros((), dtype=torch.float64, device=self.device)
        self._train_count = 0

    def training_step(self, batch: dict[str, Tensor], batch_idx: int) -> Tensor:
        """MSE on the control sequence of one batch (plus a plant part's own loss).

        ``train/loss``, the epoch's mean, is logged once, with the last batch (cheaper).
        """
        errors, out = self.policy.errors(batch)
        loss = errors.mean()
        own = self.policy.net.plant.loss(out.plant, batch["tag"])
        if own is not None:
            logged, term = own
            self.log("train/identity", logged, on_step=False, on_epoch=True, logger=False)
            loss = loss + term
        n = batch["tag"].shape[0]
        self._train_sum += loss.detach() * n
        self._train_count += n
        trainer = self._trainer  # None where the step is called outside a fit
        if trainer is not None and batch_idx + 1 == trainer.num_training_batches:
            mean = (self._train_sum / self._train_count).float()
            self.log("train/loss", mean, on_step=False, on_epoch=True, prog_bar=True, logger=False,
                     batch_size=n)  # fmt: skip
        return loss

    def on_validation_epoch_start(self) -> None:
        """Reset the per-tag error sums."""
        self._val_sse = torch.zeros_like(self._val_sse, device=self.device)
        self._val_count = torch.zeros_like(self._val_count, device=self.device)
        self._val_hits = None

    def validation_step(self, batch: dict[str, Tensor], batch_idx: int) -> None:
        """Accumulate squared errors per system tag."""
        err, out = self.policy.errors(batch)
        err = err.to(torch.float64)
        if out.plant is not None and out.plant.logits is not None:  # an identity head's
            hits = (out.plant.logits.argmax(1) == batch["tag"]).sum().to(torch.float64)
            self._val_hits = hits if self._val_hits is None else self._val_hits + hits
        self._val_sse.index_add_(0, batch["tag"], err.sum(1))
        self._val_count.index_add_(0, batch["tag"], torch.full_like(err[:, 0], err.shape[1]))

    def on_validation_epoch_end(self) -> None:
        """Log ``val/loss`` (MSE over all validation windows) and ``val/mse/<plant>``."""
        total = self._val_count.sum()
        if total == 0:
            return
        self.log("val/loss", (self._val_sse.sum() / total).float(), prog_bar=True, logger=False)
        if self._val_hits is not None:  # a part that reads the plant; windows = count / horizon
            share = self._val_hits * self.policy.horizon / total
            self.log("val/identity_acc", share.float(), logger=False)
        for tag in torch.nonzero(self._val_count).flatten().tolist():
            name = self.tag_names.get(tag, f"tag{tag}")
            mse = self._val_sse[tag] / self._val_count[tag]
            self.log(f"val/mse/{name}", mse.float(), logger=False)

    def setup(self, stage: str) -> None:
        """The rich progress bar's metrics in 3 significant digits (``.3f`` shows 1e-9 as 0)."""
        bar = self.trainer.progress_bar_callback
        if isinstance(bar, RichProgressBar):  # a copy: the default theme is shared by every bar
            bar.theme = dataclasses.replace(bar.theme, metrics_format=".3g")

    def configure_optimizers(self) -> Any:
        """The optimiser (and epoch-wise scheduler) from the Hydra partials in the hparams."""
        hp = self.hparams
        optimizer = instantiate(hp["optimizer"])(params=self.parameters())
        if not hp["scheduler"]:
            return {"optimizer": optimizer}
        scheduler = instantiate(hp["scheduler"])(optimizer=optimizer)
        return {
            "optimizer": optimizer,
            "lr_scheduler": {"scheduler": scheduler, "interval": "epoch", "frequency": 1},
        }
