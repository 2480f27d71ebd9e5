"""Data and training-loop throughput: ``python -m rgns.bench training [--json PATH]``.

One thread, one run, one synthetic 1,000-particle 2D dataset (uniform random particles, about
20 neighbours each, moving by small random walks) written through the data contract. Measures:

1. windows per second delivered by the DataModule's training loader (radius graph, noise,
   batching; ``num_workers=0``, so it is all on the measuring thread);
2. the bare model training step (loss, backward, Adam step) on batches held in memory;
3. the full Lightning Trainer (data loader with its worker, logging, checkpoint callback) on the
   same dataset and model: steps per second, timed from the first to the last measured step.

The targets are ratios from this one run: data loading well above the step rate, and the
Trainer at least 0.8 of the bare step rate.

``python -m rgns.bench training --main [--models rgns gns sep_gns]`` measures instead the main
job's preset (``experiment=main``, with ``scripts/main.sh``'s overrides) on its dataset
(``datasets/waterdrop40_main``, generated if missing): the bare training step of each model on real
windows, one thread, median of repeats, beside the step as it was before (R-GNS's memory-saving
backward, a per-parameter Adam), timed in alternation; the ratio is the speed-up. With
``--compile`` the step beside it is the same model with ``module.compile=true``
(``torch.compile(dynamic=True)`` of the network), and the time its first steps took to compile
is printed too. With ``--density-union`` it measures R-GNS 64x2's unrolled step with the density
term (``recipe=unroll``, six steps, ``density_weight=10``) beside the same step with the union of
the two radius graphs built as it was before :func:`~rgns.data.graph.edge_union`
(``torch.cat(...).unique(dim=1)``).
"""
from __future__ import annotations

import argparse
import contextlib
import json
import tempfile
import time
from pathlib import Path
from types import SimpleNamespace
from unittest import mock

import lightning as L
import numpy as np
import torch

from rgns.bench.models import scene
from rgns.data.contract import SPLITS, write_metadata, write_split
from rgns.data.datamodule import ParticleDataModule
from rgns.training.module import SimulatorModule


def synthetic_dataset(root: Path, particles: int, frames: int, trajectories: int) -> None:
    metadata, state = scene(particles, neighbours=20.0)
    rng = np.random.default_rng(0)
    start = state.position.numpy()

    def trajectory():
        steps = rng.normal(scale=1e-3, size=(frames, particles, 2))
        return np.clip(start + np.cumsum(steps, axis=0), 0.1, 0.9).astype(np.float32), np.full(particles, 5)

    for split in SPLITS:
        write_split(root / f"{split}.h5", [trajectory() for _ in range(trajectories)])
    stats = dict(vel_mean=[0.0, 0.0], vel_std=[1e-3, 1e-3], acc_mean=[0.0, 0.0], acc_std=[1.4e-3, 1.4e-3])
    write_metadata(root, dict(metadata, **stats, sequence_length=frames - 1))


class StepTimer(L.Callback):
    """Wall time from the start of step ``warmup`` to the end of the last step."""

    def __init__(self, warmup: int):
        self.warmup, self.start, self.end, self.steps = warmup, None, None, 0

    def on_train_batch_start(self, trainer, module, batch, batch_idx):
        if trainer.global_step == self.warmup:
            self.start = time.perf_counter()

    def on_train_batch_end(self, trainer, module, outputs, batch, batch_idx):
        if self.start is not None:
            self.steps += 1
            self.end = time.perf_counter()


# scripts/main.sh's per-model overrides, and what each was before the faster training step
MAIN_OVERRIDES = {"rgns": ["model.memory_saving=false", "model.couplings=pairwise"],
                  "gns": ["model.layers=4", "model.decoder=pairwise"], "sep_gns": ["model.layers=4", "model.decoder=pairwise"]}
BEFORE = {"rgns": ["model.memory_saving=true"]}
# --density-union: the unrolled stage with the density term, as the pushed stages of the staged recipes train it (docs/pretrain_recipes.md)
DENSITY = ["recipe=unroll", "module.unroll.steps=[0]", "module.unroll.lengths=[6]", "data.horizon=6",
           "density_weight=10", "model.latent=64"]


def union_by_unique(first: torch.Tensor, second: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """The density term's graph union as it was built before :func:`~rgns.data.graph.edge_union`."""
    return torch.cat([first, second], dim=1).unique(dim=1)


def main_preset(models: list[str], steps: int, overrides: list[str], compiled: bool = False,
                density_union: bool = False) -> dict:
    """Bare training steps per second of the main preset's models on its dataset, as
    ``scripts/main.sh`` trains them (its overrides, the configured fused Adam) and, beside it,
    as they were before (R-GNS's memory-saving backward, a per-parameter Adam) or, with
    ``compiled``, with ``module.compile=true``; the two timed in alternation on the same batches
    so that the ratio is measured side by side. The first 5 steps of each are warm-up (for the
    compiled one: its compilation, timed as ``compile_s``). With ``density_union`` the step
    beside it is the same configuration with :func:`union_by_unique` in the density term."""
    from hydra import compose, initialize_config_dir
    from hydra.utils import instantiate

    from rgns import config_dir

    torch.set_num_threads(1)
    warmup = 5
    result = {}
    for name in models:
        other = (["module.compile=true"] if compiled else [] if density_union
                 else [*BEFORE.get(name, []), "module.optimizer.fused=false"])
        label = "compiled" if compiled else "before"
        variants = {}
        for variant, extra in (("main", []), (label, other)):
            with initialize_config_dir(str(config_dir()), version_base="1.3"):
                cfg = compose("train", overrides=["experiment=main", f"model={name}", "data.num_workers=0",
                                                  *MAIN_OVERRIDES.get(name, []), *extra, *overrides])
            if not variants:
                datamodule = instantiate(cfg.data)
                datamodule.prepare_data()
                datamodule.setup("fit")
                loader = iter(datamodule.train_dataloader())
                batches = [next(loader) for _ in range(steps + warmup)]
            L.seed_everything(0)
            module = instantiate(cfg.module, model=cfg.model, loss=cfg.loss, metadata=datamodule.metadata,
                                 _recursive_=False)
            module.setup("fit")  # where module.compile takes effect
            module._trainer = SimpleNamespace(datamodule=datamodule, global_step=0)  # what a multi-step loss reads
            variants[variant] = (module, instantiate(cfg.module.optimizer)(module.parameters()), [])
        warm = dict.fromkeys(variants, 0.0)
        for i, batch in enumerate(batches):  # alternate: both variants see the same load
            for variant, (module, optimizer, times) in variants.items():
                before_union = density_union and variant == label
                patch = mock.patch("rgns.training.module.edge_union", union_by_unique) if before_union else None
                start = time.perf_counter()
                with patch or contextlib.nullcontext():
                    optimizer.zero_grad(set_to_none=True)
                    module._losses(batch)["loss"].backward()
                    optimizer.step()
                if i >= warmup:
                    times.append(time.perf_counter() - start)
                else:
                    warm[variant] += time.perf_counter() - start
        ms = {variant: 1e3 * float(np.median(times)) for variant, (_, _, times) in variants.items()}
        nodes = float(np.mean([b.num_nodes for b in batches]))
        edges = float(np.mean([b.edge_index.shape[1] for b in batches]))
        result[name] = {"ms_per_step": ms["main"], "steps_per_s": 1e3 / ms["main"], f"ms_per_step_{label}": ms[label],
                        "nodes_per_batch": nodes, "edges_per_batch": edges}
        if compiled:  # the compiled step beside the eager one, and what compiling cost
            result[name].update(speedup=ms["main"] / ms[label], compile_s=warm[label] - warm["main"])
            print(f"{name:<8} {ms['main']:7.1f} ms/step eager, {ms[label]:7.1f} ms compiled: "
                  f"{result[name]['speedup']:.2f}x, compiling {result[name]['compile_s']:.0f} s  ({nodes:.0f} nodes, "
                  f"{edges:.0f} edges per batch of {datamodule.batch_size})", flush=True)
        else:
            result[name]["speedup"] = ms[label] / ms["main"]
            print(f"{name:<8} {ms['main']:7.1f} ms/step ({1e3 / ms['main']:5.1f} steps/s), before {ms[label]:7.1f} ms: "
                  f"{result[name]['speedup']:.2f}x  ({nodes:.0f} nodes, {edges:.0f} edges per batch of "
                  f"{datamodule.batch_size})", flush=True)
    return result


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m rgns.bench training", description=__doc__.splitlines()[0])
    parser.add_argument("--main", action="store_true", help="the main preset's models on its dataset instead")
    parser.add_argument("--compile", action="store_true",
                        help="with --main: beside each step, the same model with module.compile=true")
    parser.add_argument("--density-union", action="store_true",
                        help="with --main: R-GNS 64x2's unrolled step with the density term, beside it the "
                             "graph union as it was (torch.unique(dim=1))")
    parser.add_argument("--models", nargs="+", default=["rgns", "gns", "sep_gns"])
    parser.add_argument("--particles", type=int, default=1000)
    parser.add_argument("--latent", type=int, default=64)
    parser.add_argument("--layers", type=int, default=5)
    parser.add_argument("--steps", type=int, default=30, help="measured steps (after 5 warm-up steps)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.main:
        if args.density_union:
            result = main_preset(["rgns"], args.steps, DENSITY, density_union=True)
        else:
            result = main_preset(args.models, args.steps, [], compiled=args.compile)
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps(result, indent=2) + "\n")
        return
    torch.set_num_threads(1)
    warmup = 5

    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "data"
        synthetic_dataset(root, args.particles, frames=40, trajectories=2)
        model_cfg = {"_target_": "rgns.models.RGNS", "latent": args.latent, "layers": args.layers}
        loss_cfg = {"_target_": "rgns.training.losses.LossDesign", "name": "DL4"}
        optimizer = {"_target_": "torch.optim.Adam", "_partial_": True, "lr": 1e-4}

        # 1. data: windows per second
        datamodule = ParticleDataModule(str(root), num_workers=0)
        datamodule.setup("fit")
        loader = iter(datamodule.train_dataloader())
        next(loader)
        start = time.perf_counter()
        batches = [next(loader) for _ in range(args.steps)]
        windows_per_s = args.steps * datamodule.batch_size / (time.perf_counter() - start)

        # 2. the bare step, on batches in memory
        L.seed_everything(0)
        module = SimulatorModule(model_cfg, datamodule.metadata, loss_cfg, optimizer)
        adam = torch.optim.Adam(module.parameters(), lr=1e-4)

        def bare_step(batch):
            adam.zero_grad(set_to_none=True)
            module._losses(batch)["loss"].backward()
            adam.step()

        for batch in batches[:warmup]:
            bare_step(batch)
        start = time.perf_counter()
        for batch in batches:
            bare_step(batch)
        bare_steps_per_s = len(batches) / (time.perf_counter() - start)

        # 3. the full Trainer: its loader (one worker), logging, last-checkpoint callback
        L.seed_everything(0)
        module = SimulatorModule(model_cfg, datamodule.metadata, loss_cfg, optimizer)
        timer = StepTimer(warmup)
        trainer = L.Trainer(
            accelerator="cpu", max_steps=warmup + args.steps, logger=L.pytorch.loggers.TensorBoardLogger(tmp),
            callbacks=[timer, L.pytorch.callbacks.ModelCheckpoint(dirpath=Path(tmp) / "ckpt", save_last=True)],
            limit_val_batches=0, log_every_n_steps=20, enable_progress_bar=False, enable_model_summary=False,
        )
        trainer.fit(module, datamodule=ParticleDataModule(str(root), num_workers=1))
        trainer_steps_per_s = timer.steps / (timer.end - timer.start)

    result = {
        "particles": args.particles,
        "model": f"R-GNS {args.latent}x{args.layers}",
        "windows_per_s": windows_per_s,
        "bare_steps_per_s": bare_steps_per_s,
        "trainer_steps_per_s": trainer_steps_per_s,
        "data_over_training": windows_per_s / (bare_steps_per_s * datamodule.batch_size),
        "trainer_over_bare": trainer_steps_per_s / bare_steps_per_s,
    }
    print(f"{'measure':<46}{'value':>10}")
    print(f"{'windows/s from the DataModule (1 thread)':<46}{windows_per_s:>10.1f}")
    print(f"{'bare training steps/s (batch 2)':<46}{bare_steps_per_s:>10.2f}")
    print(f"{'Trainer steps/s (batch 2)':<46}{trainer_steps_per_s:>10.2f}")
    print(f"{'data / training (windows per window trained)':<46}{result['data_over_training']:>10.2f}")
    print(f"{'Trainer / bare (target >= 0.8)':<46}{result['trainer_over_bare']:>10.2f}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=2) + "\n")
