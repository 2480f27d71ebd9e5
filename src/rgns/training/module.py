"""The LightningModule: one training step computes the forward loss (newest velocity) and, for
bidirectional models, the inverse loss (oldest velocity) on the same batch and graph."""
from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import lightning as L
import matplotlib
import torch
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from rgns.data.contract import KINEMATIC, metadata_differences
from rgns.data.graph import edge_union
from rgns.data.windows import noise_level, random_walk_noise, scale_position_noise
from rgns.models import State
from rgns.targets import UnsafeConfigError, check_checkpoint_configs
from rgns.training.losses import density_error
from rgns.training.recipes import Pushforward, Unroll
from rgns.training.rollouts import forward_rollout, inverse_then_forward

matplotlib.use("Agg")
log = logging.getLogger(__name__)


MULTISTEP_TARGETS = ("position", "velocity", "acceleration")


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
        pushforward: ``{steps, unrolls, probs}`` of a :class:`~rgns.training.recipes.Pushforward`
            schedule (forward loss only); needs ``data.lead`` >= its largest unroll.
        unroll: ``{steps, lengths}`` of an :class:`~rgns.training.recipes.Unroll` schedule: the
            forward loss through that many steps; needs ``data.horizon`` >= its longest.
        lr_reference_batch: scale the optimiser's learning rate linearly with the graphs per
            optimisation step (``data.batch_size`` x DDP ranks) over this reference batch (e.g.
            2, the batch the lr was tuned at); ``None`` keeps the lr as given.
        position_correction, position_noise, noise_low: the noise variants of
            :class:`~rgns.data.windows.WindowDataset`, applied to the start frame of the
            pushforward and unrolled losses as the datamodule applies them to one-step windows.
        density_weight: weight of a density term in the pushforward and unrolled losses: at every
            step with gradients, the relative error of the predicted particles' kernel density
            (:func:`~rgns.training.losses.density_error`, support the connectivity radius) against
            the clean true frame's. Since the input is noisy and the position targets move with
            its noise, this asks the network to restore the true density, that is to push
            squeezed neighbourhoods apart and pull stretched ones together, and nothing else
            (0: off; needs ``pushforward`` or ``unroll``, and acts in the training steps that take
            the multi-step path: an unrolled length above 1 or a pushforward draw above 0).
        wall_gradient: ``"stop"`` or ``"through"``: how the gradients of those losses cross the
            model's hard walls (:attr:`~rgns.models.base.Simulator.wall_gradient`).
        multistep_target: what each step with gradients of the pushforward and unrolled losses
            is asked for, from the state the model reached: ``"position"`` the true next
            position (the error of the predicted position, so a drifted state is asked to
            undo all its drift in one step); ``"velocity"`` the true next velocity (the drift
            of the velocity is undone, the position's is not, as GNS's noise correction does);
            ``"acceleration"`` the true trajectory's own acceleration at that frame, whatever
            the state (as LagrangeBench's pushforward does). All in acceleration-std units.
        compile: run the model's network functions through ``torch.compile(dynamic=True)`` in
            training steps (:meth:`~rgns.models.base.Simulator.compile_network`); validation and
            a simulator loaded from the checkpoint run eager.
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
        pushforward: dict | None = None,
        unroll: dict | None = None,
        lr_reference_batch: int | None = None,
        position_correction: float = 0.0,
        position_noise: float = 1.0,
        noise_low: float = 1.0,
        density_weight: float = 0.0,
        wall_gradient: str = "stop",
        multistep_target: str = "position",
        compile: bool = False,
    ):
        super().__init__()
        # Hydra hands over DictConfigs: store plain values, so checkpoints load with weights_only
        model, metadata, loss, optimizer, scheduler, pushforward, unroll = (
            OmegaConf.to_container(c, resolve=True) if isinstance(c, DictConfig) else c
            for c in (model, metadata, loss, optimizer, scheduler, pushforward, unroll)
        )
        self.save_hyperparameters()
        model = dict(model)
        train_inverse = model.pop("train_inverse", True)
        # _recursive_=False: the metadata is data (a generated dataset's carries its scene's _target_,
        # which a recursive instantiate would build, Taichi and all) and no model config nests a target
        self.model = instantiate(model, metadata=metadata, history=history, noise_std=noise_std, _recursive_=False)
        self.train_inverse = bool(train_inverse) and self.model.bidirectional
        if wall_gradient not in ("stop", "through"):
            raise ValueError(f"wall_gradient must be 'stop' or 'through', got {wall_gradient!r}")
        self.model.wall_gradient = wall_gradient
        if multistep_target not in MULTISTEP_TARGETS:
            raise ValueError(f"multistep_target must be one of {MULTISTEP_TARGETS}, got {multistep_target!r}")
        self.loss = instantiate(loss)
        self.pushforward = Pushforward(**pushforward) if pushforward else None
        self._pushed = 0  # the latest training batch's pushed steps, logged as train/pushed
        self.unroll = Unroll(**unroll) if unroll else None
        if density_weight < 0:
            raise ValueError(f"density_weight={density_weight}: a loss weight cannot be negative")
        if density_weight and self.pushforward is None and self.unroll is None:
            raise ValueError("density_weight acts in the multi-step losses only: set recipe=unroll or "
                             "recipe=pushforward with it")

    def setup(self, stage: str) -> None:
        if self.hparams.compile and not self.model.compiled:
            self.model.compile_network(dynamic=True)  # graph sizes change with every batch

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

    def _multistep_forward(self, batch, pushed: int, length: int) -> dict[str, torch.Tensor]:
        """The forward loss terms after ``pushed`` steps without gradients, through ``length``
        steps with them (:mod:`rgns.training.recipes`), averaged over the ``length`` steps."""
        k = self.hparams.history
        frames = getattr(batch, "frames", None)  # [N, lead + k + 1 + horizon, D], p^t at index lead + k
        lead = int(getattr(self.trainer.datamodule, "lead", 0))
        needed = f"data.lead >= {pushed} and data.horizon >= {length}"
        if frames is None or lead < pushed or frames.shape[1] - lead - k - 1 < length:
            raise ValueError(f"pushforward/unroll need windows with more frames: set {needed}")
        moving = batch.particle_type != KINEMATIC
        start = lead + k - pushed  # index of the frame the pushforward starts at
        # an early window (data.early_windows) has only lead_frames real frames before its history:
        # it starts `wait` pushed steps later, from the first state its real frames hold (history
        # from the trajectory's frame 0), and is held at that state until then
        lead_frames = getattr(batch, "lead_frames", None)
        wait = None if lead_frames is None else pushed - lead_frames.clamp(max=pushed)  # [N]
        if wait is None or not bool(wait.any()):
            wait = None
            window = frames[:, start - k : start + 1].transpose(0, 1)  # [k + 1, N, D], clean
        else:
            index = start + wait[:, None] + torch.arange(-k, 1, device=frames.device)  # [N, k + 1]
            window = frames.gather(1, index[..., None].expand(-1, -1, frames.shape[2])).transpose(0, 1)
        velocity = window[1:] - window[:-1]  # [k, N, D]
        if self.hparams.noise_std > 0:  # a level per window (graph) of the batch, as the one-step windows draw theirs
            level = noise_level(self.hparams.noise_low, size=int(batch.num_graphs))
            level = level if isinstance(level, float) else level[batch.batch.cpu()]
            velocity = velocity + random_walk_noise(tuple(velocity.shape), self.hparams.noise_std, moving.cpu(),
                                                    level).to(velocity)
        # the start frame, noisy (its share of the noise scaled as in the one-step windows)
        noisy_last = scale_position_noise(window[0] + velocity.sum(0), window[-1], self.hparams.position_noise)
        # the targets move with the start frame's noise (as in GNS), less the corrected fraction
        offset = (1 - self.hparams.position_correction) * (noisy_last - window[-1])
        state = initial = State(noisy_last, velocity.transpose(0, 1).contiguous(), batch.particle_type, batch.batch)
        # the steps every window of the batch is still held through change nothing: skip them
        first = 0 if wait is None else int(wait.min())
        with torch.no_grad():
            for j in range(first, pushed):
                state = self.model.step(state, kinematic_position=frames[:, start + j + 1])
                if wait is not None:  # the windows whose own start (frame start + wait) is still ahead
                    hold = wait > j
                    state = State(torch.where(hold[:, None], initial.position, state.position),
                                  torch.where(hold[:, None, None], initial.velocity_history, state.velocity_history),
                                  state.particle_type, state.batch)
        scale = self.model.acc_std_noisy
        totals: dict[str, torch.Tensor] = {}
        for j in range(length):
            previous, reference = state.position, state.velocity_history[:, -1]  # p^{t+j}, v^{t+j} (predicted)
            truth = frames[:, lead + k + j - 1 : lead + k + j + 2]  # the true p^{t+j-1}, p^{t+j}, p^{t+j+1}
            state = self.model.step(state, kinematic_position=frames[:, lead + k + j + 1])
            # the predicted acceleration; gradients reach every step through the positions and
            # histories of the earlier ones
            change = (state.velocity_history[:, -1] - reference) / scale
            if self.hparams.multistep_target == "position":  # change - target_change: the position's error
                target_change = (truth[:, 2] + offset - previous - reference) / scale  # noise-shifted p^{t+j+1}
            elif self.hparams.multistep_target == "velocity":  # ... the next velocity's error
                target_change = (truth[:, 2] - truth[:, 1] - reference) / scale
            else:  # the true acceleration
                target_change = (truth[:, 2] - 2 * truth[:, 1] + truth[:, 0]) / scale
            terms = self.loss(change[moving], target_change[moving], batch.batch[moving])
            if self.hparams.density_weight:
                clean = frames[:, lead + k + j + 1]  # the true p^{t+j+1}, without the start frame's noise
                pairs = edge_union(self.model.graph(state.position.detach(), batch.batch),
                                   self.model.graph(clean, batch.batch), len(clean))
                terms["density"] = density_error(state.position, clean, pairs, self.model.radius, moving)
                terms["loss"] = terms["loss"] + self.hparams.density_weight * terms["density"]
            for key, value in terms.items():
                totals[key] = totals.get(key, 0) + value / length
        return totals

    def _losses(self, batch) -> dict[str, torch.Tensor]:
        pushed = self.pushforward.draw(self.global_step) if self.pushforward is not None and self.training else 0
        length = self.unroll.length(self.global_step) if self.unroll is not None and self.training else 1
        self._pushed = pushed
        if pushed or length > 1:
            terms = {f"forward_{key}": value for key, value in self._multistep_forward(batch, pushed, length).items()}
            loss = terms["forward_loss"]
            if self.train_inverse:
                terms.update({f"inverse_{key}": value for key, value in self._direction(batch, "inverse").items()})
                loss = loss + self.hparams.inverse_weight * terms["inverse_loss"]
            terms["loss"] = loss
            return terms
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
        if self.pushforward is not None:
            self.log("train/pushed", float(self._pushed), batch_size=batch.num_graphs)
        return terms["loss"]

    def on_before_optimizer_step(self, optimizer) -> None:
        # the whole gradient's norm as the loss made it, before `trainer.gradient_clip_val` clips it:
        # a batch pushed through a long rollout can have 10-100 times a one-step batch's
        grads = [p.grad.detach() for p in self.parameters() if p.grad is not None]
        if grads:
            self.log("train/grad_norm", torch.nn.utils.get_total_norm(grads), batch_size=1)

    def validation_step(self, batch, batch_idx: int) -> None:
        # eager: a few no-grad rollouts every validation would not repay compiling their graphs
        with torch.compiler.set_stance("force_eager"):
            self._validate(batch, batch_idx)

    def _validate(self, batch, batch_idx: int) -> None:
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
        if self.hparams.lr_reference_batch:  # linear scaling: lr x (graphs per step / reference)
            datamodule = getattr(self.trainer, "datamodule", None)
            batch = getattr(datamodule, "batch_size", None)
            if batch is None:
                raise ValueError("lr_reference_batch needs a datamodule with a batch_size")
            factor = batch * self.trainer.world_size / self.hparams.lr_reference_batch
            for group in optimizer.param_groups:
                group["lr"] *= factor
                group["initial_lr"] = group["lr"]
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
        # also as the run gave it, when relative: the same dataset in a checkout on another machine
        relative = root is not None and not Path(root).is_absolute()
        checkpoint["data_root_relative"] = Path(root).as_posix() if relative else None


class CheckpointError(ValueError):
    """A file is not a readable rgns checkpoint, or does not fit the data it is used on; the
    message names the file and what is wrong."""


_NOT_A_CHECKPOINT = ("a PyTorch file, but not an rgns training checkpoint (it needs a state_dict and "
                     "hyper_parameters with 'model' and 'metadata', as train.py writes)")


def load_simulator(path: str, map_location: str = "cpu"):
    """The trained simulator (a plain ``nn.Module``, eval mode) and its checkpoint's extras.

    The file is read once, with ``torch.load(weights_only=True)``: tensors and plain containers,
    all that train.py writes, and never pickled code; the module is rebuilt from what was read.
    Raises :class:`CheckpointError` naming the file when it is not a readable checkpoint
    (truncated, not a PyTorch file, holding pickled objects) or not one of a :class:`SimulatorModule`."""
    extras = _read_checkpoint(path, "checkpoint")
    hparams = extras.get("hyper_parameters")
    if not isinstance(hparams, dict) or not {"model", "metadata"} <= set(hparams):
        raise CheckpointError(f"{path}: {_NOT_A_CHECKPOINT}")
    try:
        module = SimulatorModule(**hparams)
        module.load_state_dict(extras["state_dict"])
    except Exception as err:
        raise CheckpointError(f"{path}: an rgns checkpoint this code cannot rebuild its model from "
                              f"({type(err).__name__}: {err})") from err
    return module.model.to(map_location).eval(), {
        "data_root": extras.get("data_root"),
        "data_root_relative": extras.get("data_root_relative"),
        "global_step": extras.get("global_step"),
        "hparams": dict(module.hparams),
    }


def warm_start(module: SimulatorModule, path: str, grow: bool = False) -> None:
    """Load the weights of the checkpoint at ``path`` into ``module`` (and nothing else: the
    optimiser, schedule and step count of the run start afresh). With weight averaging the
    checkpoint's weights are the averaged ones, which is what its validation scored.

    Raises :class:`CheckpointError` naming the file when it is not a readable rgns checkpoint or
    its network does not fit the module's (another model, width or depth). Parameters the model
    lists in ``warm_start_optional`` (an option that starts as a no-op) keep their initial values
    when the checkpoint lacks them. With ``grow`` the model may be deeper than the checkpoint's:
    the layers it adds (``warm_start_added``: R-GNS's reversible blocks past the checkpoint's,
    which start as the identity) keep their initial values, so it starts computing what the
    checkpoint's model computes; a model that adds no such layers is refused."""
    extras = _read_checkpoint(path, "checkpoint to start from (init_from)")
    state = extras["state_dict"]
    differences = _data_differences(extras, module)
    if differences:  # a fine-tune on other data is a use of init_from=; said, not refused
        log.warning("%s: trained on other data than this run's: %s", path, "; ".join(differences))
    own = module.state_dict()
    optional = {f"model.{name}" for name in module.model.warm_start_optional()}
    if grow:
        present = {name.removeprefix("model.") for name in state if name.startswith("model.")}
        added = {f"model.{name}" for name in module.model.warm_start_added(present)}
        if not added:
            raise CheckpointError(f"{path}: init_grow=true, but this run's {type(module.model).__name__} adds no "
                                  "layers that start as the identity to the checkpoint's (the same depth, a model "
                                  "that cannot grow, or zero_init=false): drop init_grow or raise model.layers")
        optional |= added
    state = {**{name: own[name] for name in optional if name not in state}, **state}
    try:
        module.load_state_dict(state)
    except RuntimeError as err:
        first = " ".join(str(err).split())[:600]
        raise CheckpointError(f"{path}: its weights do not fit this run's model (another model, width or depth "
                              f"than the run's config?): {first}") from None


def check_resume(module: SimulatorModule, path: str) -> None:
    """Refuse ``resume=<path>`` before training when the run could not continue it as it was:
    an unreadable file, another model config than this run's (``model.latent``, another model),
    weights that do not fit, or other data (:func:`~rgns.data.contract.metadata_differences`
    between the checkpoint's metadata and this run's dataset). Lightning would otherwise fail
    deep inside with torch's raw state-dict errors, or train on without a word.

    Raises :class:`CheckpointError` (or FileNotFoundError) naming the file and what differs."""
    extras = _read_checkpoint(path, "checkpoint to resume (resume=)")
    hparams = extras.get("hyper_parameters")
    if not isinstance(hparams, dict) or not isinstance(hparams.get("model"), dict):
        raise CheckpointError(f"{path}: {_NOT_A_CHECKPOINT}")
    theirs, ours = hparams["model"], dict(module.hparams["model"])
    if theirs != ours:
        keys = sorted(set(theirs) | set(ours), key=str)
        changed = [f"model.{k}: {theirs.get(k, '(unset)')!r} in the checkpoint, {ours.get(k, '(unset)')!r} here"
                   for k in keys if theirs.get(k) != ours.get(k)]
        raise CheckpointError(f"{path}: resume= continues a run with its own model, but this run's differs "
                              f"({'; '.join(changed[:4])}): drop those overrides, or start a new run from its "
                              "weights with init_from=")
    own = module.state_dict()
    state = extras["state_dict"]
    misfits = sorted(set(own) ^ set(state)) + sorted(k for k in set(own) & set(state)
                                                      if tuple(own[k].shape) != tuple(state[k].shape))
    if misfits:
        raise CheckpointError(f"{path}: its weights do not fit this run's model ({', '.join(misfits[:3])}"
                              f"{', ...' if len(misfits) > 3 else ''})")
    differences = _data_differences(extras, module)
    if differences:
        raise CheckpointError(f"{path}: trained on other data than this run's ({'; '.join(differences)}): resume= "
                              "continues a run on its own dataset; start a new run from its weights with init_from= "
                              "to train on this one")


def _data_differences(extras: dict, module: SimulatorModule) -> list[str]:
    """:func:`~rgns.data.contract.metadata_differences` between the metadata a checkpoint
    (``extras``, as read) was trained with and the module's; none where it records none."""
    trained = (extras.get("hyper_parameters") or {}).get("metadata")
    return metadata_differences(trained, module.hparams["metadata"]) if isinstance(trained, dict) else []


def _read_checkpoint(path: str, role: str) -> dict:
    """What the checkpoint file ``path`` holds, checked to have a ``state_dict``; ``role`` names
    the file in the error when it is missing ("checkpoint to start from (init_from)").

    Raises FileNotFoundError, or :class:`CheckpointError` naming the file when it is not a
    readable PyTorch file or holds no state_dict."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{path}: {role} not found")
    extras = _read_plain(path)
    if not isinstance(extras, dict) or not isinstance(extras.get("state_dict"), dict):
        raise CheckpointError(f"{path}: {_NOT_A_CHECKPOINT}")
    hparams = extras.get("hyper_parameters")
    if hparams is not None:
        if not isinstance(hparams, dict):
            raise CheckpointError(f"{path}: {_NOT_A_CHECKPOINT}")
        try:  # before anything is built from them: every _target_ one of rgns's own (rgns.targets)
            check_checkpoint_configs(hparams, str(path))
        except UnsafeConfigError as err:
            raise CheckpointError(str(err)) from None
    return extras


def _read_plain(path: str):
    """What the PyTorch file ``path`` holds, read with ``weights_only=True`` onto the CPU.

    Raises :class:`CheckpointError` naming the file, and the pickled object where one stopped
    the reader, when it cannot be read so."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # whatever torch's readers meet: OSError, EOFError, KeyError, UnpicklingError, ...
        message = str(err)
        unsafe = re.search(r"(?:GLOBAL|Unsupported class) ([\w.]+)", message)  # torch's words for a pickled object
        if unsafe:
            raise CheckpointError(f"{path}: holds a pickled Python object ({unsafe[1]}), not only the tensors and "
                                  "plain containers train.py writes; not loaded, as unpickling it could run any code "
                                  "(rgns reads checkpoints with torch.load(weights_only=True))") from None
        if "WeightsUnpickler error:" in message:  # the reason, without torch's advice to load with weights_only=False
            message = message.split("WeightsUnpickler error:")[1].split("Check the documentation")[0]
        reason = f"{type(err).__name__}: {' '.join(message.split())}"
        raise CheckpointError(f"{path}: not a readable checkpoint ({reason}); the file may be truncated (an interrupted "
                              "write or copy) or not a checkpoint at all") from None
