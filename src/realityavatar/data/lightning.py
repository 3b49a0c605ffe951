"""The data's Lightning side, for training only (train.py): TrainingData, the LightningDataModule that hands a set-up
AvatarDataModule (data/datamodule.py, no Lightning) to trainer.fit, and SamplerFeedback, the callback that passes the
training losses to the sampler. Export, animate, the viewer and evaluation read AvatarDataModule without them."""

from __future__ import annotations

import pytorch_lightning as pl
import torch


class TrainingData(pl.LightningDataModule):
    """A set-up AvatarDataModule (data/datamodule.py, no Lightning) as trainer.fit reads it: its loaders, made for the
    trainer's device (pinned batches, the training set kept on a GPU with data.device_cache), and the batch hooks."""

    def __init__(self, data) -> None:
        super().__init__()
        self.data = data

    @property
    def train_sampler(self):  # SamplerFeedback's
        return self.data.train_sampler

    def prepare_data(self) -> None:
        self.data.prepare_data()

    def setup(self, stage: str) -> None:
        self.data.device = self.trainer.strategy.root_device
        self.data.setup(stage)

    def train_dataloader(self):
        return self.data.train_dataloader()

    def val_dataloader(self):
        return self.data.val_dataloader()

    def on_before_batch_transfer(self, batch: dict, dataloader_idx: int) -> dict:
        """Before a batch moves to the device, image sizes become host ints (read from a GPU tensor, each would make
        the training step wait for the device). Poses need no check here: every window comes from a PoseTable, which
        refused non-finite poses when it was built. A training batch of views_per_step cameras per frame says so
        (`views_per_frame`, checked on the host frames): Avatar.render_batch poses each frame once."""
        out = {**batch, "width": batch["width"].tolist(), "height": batch["height"].tolist()}
        V = self.data.views_per_step
        if V > 1 and self.trainer is not None and self.trainer.training:
            f = batch["frame"].reshape(-1, V)
            if not bool((f == f[:, :1]).all()):
                raise RuntimeError(f"data.views_per_step={V}: a training batch mixes frames {f.tolist()}")
            out["views_per_frame"] = V
        return out

    def transfer_batch_to_device(self, batch: dict, device: torch.device, dataloader_idx: int) -> dict:
        """The trainer's move of a batch; a batch of the training set kept on the device (device_cache) brings only
        its host entries and takes its tensors from there."""
        moved = super().transfer_batch_to_device(batch, device, dataloader_idx)
        kept = self.data.device_samples
        if kept is None or "pixels" in batch:  # a batch of the host's samples
            return moved
        return {**moved, **kept.gather(batch["index"].tolist())}


class SamplerFeedback(pl.Callback):
    """Passes each training step's per-image losses to the training sampler (`observe`). Losses on a GPU are kept
    there and passed every `log_every_n_steps` steps (with the logging): each read of the device waits for it."""

    def __init__(self) -> None:
        self._pending: list[tuple[torch.Tensor, torch.Tensor]] = []

    def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:
        sampler = getattr(trainer.datamodule, "train_sampler", None) if trainer.datamodule is not None else None
        if sampler is None:
            return
        if not isinstance(outputs, dict) or "image_loss" not in outputs or "index" not in batch:
            return
        loss = outputs["image_loss"].detach()
        self._pending.append((batch["index"].detach(), loss))
        if loss.device.type == "cpu" or trainer.global_step % max(int(trainer.log_every_n_steps), 1) == 0:
            index, value = (torch.cat(t).cpu() for t in zip(*self._pending))  # in step order: one copy each
            sampler.observe(index, value)
            self._pending.clear()
