"""The LightningModule: one training step computes the forward loss (newest velocity) and, for
bidirectional models, the inverse loss (oldest velocity) on the same batch and graph."""
from __future__ import annotations

import math
from pathlib import Path

import lightning as L
import matplotlib
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from rgns.data.contract import KINEMATIC
from rgns.training.rollouts import forward_rollout, inverse_then_forward

matplotlib.use("Agg")


class SimulatorModule(L.LightningModule):
    """Trains any rgns simulator (GNS, R-GNS, R-GNS†, Sep-GNS).

    Args:
        model: config of the simulator (``_target_`` + sizes); the key ``train_inverse: false``
            trains a bidirectional model forward only (R-GNS†).
        metadata: the dataset's metadata (normalisation, radius, bounds).
        loss: config of a :class:`~rgns.training.losses.LossDesign`.
        optimizer, scheduler: partial configs; the scheduler gets ``T_max`` = the run's steps.
        history, noise_std: k and the random-walk noise std of the data.
        inverse_weight: weight of the inverse loss against the forward loss.
        val_rollout_steps: length of the forward rollout validated each epoch.
        val_consistency_steps: K of the inverse-then-forward consistency validated each epoch.
        val_trajectories: how many validation trajectories those rollouts use.
    """

    def __init__(
        self,
        model: dict,
        metadata: dict,
        loss: dict,
        optimizer: dict,
        scheduler: dict | None = None,
        history: int = 5,
        noise_std: float = 6.7e-4,
        inverse_weight: float = 1.0,
        val_rollout_steps: int = 20,
        val_consistency_steps: int = 10,
        val_trajectories: int = 2,
    ):
        super().__init__()
        # Hydra hands over DictConfigs: store plain values, so checkpoints load with weights_only
        model, metadata, loss, optimizer, scheduler = (
            OmegaConf.to_container(c, resolve=True) if isinstance(c, DictConfig) else c
            for c in (model, metadata, loss, optimizer, scheduler)
        )
        self.save_hyperparameters()
        model = dict(model)
        train_inverse = model.pop("train_inverse", True)
        self.model = instantiate(model, metadata=metadata, history=history, noise_std=noise_std)
        self.train_inverse = bool(train_inverse) and self.model.bidirectional
        self.loss = instantiate(loss)

    # -- one step, both directions ------------------------------------------------------------
    def _direction(self, batch, direction: str, predicted: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """The loss terms of one direction (its prediction made here unless given)."""
        moving = batch.particle_type != KINEMATIC
        graph = (batch.particle_type, batch.edge_index, batch.batch)
        if direction == "forward":
            reference, target = batch.forward_input[:, -1].clone(), batch.forward_target  # v^t, v^{t+1}
            if predicted is None:
                predicted = self.model.next_velocity(batch.pos, batch.forward_input, *graph)
        else:
            reference, target = batch.inverse_input[:, 0].clone(), batch.inverse_target  # v^{t-k+2}, v^{t-k+1}
            if predicted is None:
                predicted = self.model.oldest_velocity(batch.pos, batch.inverse_input, *graph)
        scale = self.model.acc_std_noisy
        change, target_change = (predicted - reference) / scale, (target - reference) / scale
        return self.loss(change[moving], target_change[moving], batch.batch[moving])

    def _losses(self, batch) -> dict[str, torch.Tensor]:
        if self.train_inverse:  # both predictions in one call, so a model can share work between them
            forward, inverse = self.model.both_velocities(batch.pos, batch.forward_input, batch.inverse_input,
                                                          batch.particle_type, batch.edge_index, batch.batch)
        else:
            forward = inverse = None
        terms = {f"forward_{key}": value for key, value in self._direction(batch, "forward", forward).items()}
        loss = terms["forward_loss"]
        if self.train_inverse:
            terms.update({f"inverse_{key}": value for key, value in self._direction(batch, "inverse", inverse).items()})
            loss = loss + self.hparams.inverse_weight * terms["inverse_loss"]
        terms["loss"] = loss
        return terms

    def training_step(self, batch, batch_idx: int) -> torch.Tensor:
        terms = self._losses(batch)
        if not torch.isfinite(terms["loss"]):
            raise FloatingPointError(
                f"non-finite training loss ({terms['loss'].item()}) at step {self.global_step}: training "
                "stopped; the checkpoints already written are untouched (lower the learning rate or "
                "resume from the last good one)"
            )
        self.log_dict({f"train/{k}": v.detach() for k, v in terms.items() if k != "loss"}, batch_size=batch.num_graphs)
        self.log("train/loss", terms["loss"].detach(), batch_size=batch.num_graphs, prog_bar=True)
        return terms["loss"]

    def validation_step(self, batch, batch_idx: int) -> None:
        if batch_idx == 0:  # here, not at epoch end: callbacks that swap weights in (EMA) have done so
            self._validation_rollouts()
        with torch.no_grad():
            terms = self._losses(batch)
        if self.model.bidirectional and not self.train_inverse:  # R-GNS†: still measure its inverse
            terms.update({f"inverse_{k}": v for k, v in self._direction(batch, "inverse").items()})
        self.log_dict({f"val/{k}": v for k, v in terms.items()}, batch_size=batch.num_graphs, sync_dist=True)

    # -- rollouts on validation trajectories ----------------------------------------------------
    @torch.no_grad()
    def _validation_rollouts(self) -> None:
        """Rollout and consistency MSE on the validation trajectories, logged for the epoch. Run at
        the first validation step, inside the window in which weight-averaging callbacks
        (``lightning.pytorch.callbacks.WeightAveraging``) validate the averaged weights: they swap
        them back before the module's ``on_validation_epoch_end``."""
        datamodule = getattr(self.trainer, "datamodule", None)
        trajectories = getattr(datamodule, "valid_trajectories", None)
        if trajectories is None or self.trainer.sanity_checking:
            return
        k, steps, consistency = self.hparams.history, self.hparams.val_rollout_steps, self.hparams.val_consistency_steps
        rollout_mse, consistency_mse, shown = [], [], None
        for i in range(min(self.hparams.val_trajectories, len(trajectories))):
            data = trajectories[i]
            position, particle_type = data.position.to(self.device), data.particle_type.to(self.device)
            n = min(steps, len(position) - k - 1)
            if n > 0:
                predicted = forward_rollout(self.model, position, particle_type, k, n)
                rollout_mse.append((predicted - position[k + 1 : k + 1 + n]).pow(2).mean())
                shown = shown or (position[k + n], predicted[-1], particle_type)
            K = min(consistency, len(position) - 2 * k - 1)
            if self.model.bidirectional and K > 0:
                _, resimulated = inverse_then_forward(self.model, position, particle_type, k, K)
                consistency_mse.append((resimulated[-1] - position[k + K]).pow(2).mean())
        if rollout_mse:
            self.log("val/rollout_mse", torch.stack(rollout_mse).mean(), sync_dist=True, batch_size=1)
        if consistency_mse:
            self.log("val/consistency_mse", torch.stack(consistency_mse).mean(), sync_dist=True, batch_size=1)
        if shown is not None:
            self._log_rollout_figure(*shown)

    def _log_rollout_figure(self, truth: torch.Tensor, predicted: torch.Tensor, particle_type: torch.Tensor) -> None:
        experiment = getattr(self.logger, "experiment", None)
        if not hasattr(experiment, "add_figure") or self.trainer.global_rank != 0:
            return
        import matplotlib.pyplot as plt

        bounds = self.model.bounds.cpu()
        fig, axes = plt.subplots(1, 2, figsize=(8, 4), sharex=True, sharey=True)
        for ax, points, title in zip(axes, (truth, predicted), ("ground truth", "rollout")):
            points = points.cpu()
            ax.scatter(points[:, 0], points[:, 1], s=2, c=particle_type.cpu(), cmap="tab10", vmin=0, vmax=9)
            ax.set_title(f"{title}, step {self.hparams.val_rollout_steps}")
            ax.set_xlim(*bounds[0].tolist())
            ax.set_ylim(*bounds[1].tolist())
            ax.set_aspect("equal")
        experiment.add_figure("val/rollout", fig, global_step=self.global_step)
        plt.close(fig)

    # -- optimisation -----------------------------------------------------------------------------
    def configure_optimizers(self):
        optimizer = instantiate(self.hparams.optimizer)(self.parameters())
        if not self.hparams.scheduler:
            return optimizer
        total = self.trainer.estimated_stepping_batches
        total = int(total) if math.isfinite(total) else 1_000_000
        scheduler = instantiate(self.hparams.scheduler)(optimizer, T_max=max(total, 1))
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        checkpoint["world_size"] = self.trainer.world_size
        root = getattr(getattr(self.trainer, "datamodule", None), "root", None)
        checkpoint["data_root"] = None if root is None else str(Path(root).resolve())


def load_simulator(path: str, map_location: str = "cpu"):
    """The trained simulator (a plain ``nn.Module``, eval mode) and its checkpoint's extras."""
    module = SimulatorModule.load_from_checkpoint(path, map_location=map_location)
    extras = torch.load(path, map_location="cpu", weights_only=False)
    return module.model.eval(), {
        "data_root": extras.get("data_root"),
        "global_step": extras.get("global_step"),
        "hparams": dict(module.hparams),
    }
