"""The methods an evaluation compares: trained checkpoints (found one by one or under a
folder, e.g. a Hydra multirun) and training-free baselines, each with a label like the paper's
("R-GNS 128x10", "R-GNS† 128x10", "GNS 128x10", "Sep-GNS 128x10"; a baseline's own ``label``).

What the tasks use of a method: ``label``, ``trained``, ``bidirectional``, ``parameters``,
``stride``, ``model`` (a :class:`~rgns.models.Simulator`) and :meth:`Method.forward_rollout`. The
solver references (:mod:`rgns.evaluation.references`) offer the same, with ``model = None``
(``stride`` absent: 1)."""
from __future__ import annotations

import argparse
import copy
import logging
from dataclasses import dataclass, field, replace
from pathlib import Path

import yaml
from hydra.utils import get_class, instantiate
from torch import Tensor

from rgns.models import RGNS, Simulator, count_parameters
from rgns.training.module import CheckpointError, load_simulator
from rgns.errors import ConfigError
from rgns.training.rollouts import forward_rollout

log = logging.getLogger(__name__)

# display names of the trained simulators, by class name (labels only: models are built by _target_)
@dataclass
class Method:
    label: str
    model: Simulator
    data_root: str | None  # the dataset its checkpoint was trained on, absolute (see trained_on)
    source: str  # checkpoint path, or "baseline"
    info: dict = field(default_factory=dict)
    data_root_relative: str | None = None  # the same, as its run gave it, when relative
    trained_metadata: dict | None = None  # the metadata of the data it was trained on (checkpoints)

    @property
    def parameters(self) -> int:
        return count_parameters(self.model)

    @property
    def trained(self) -> bool:
        return self.source != "baseline"

    @property
    def bidirectional(self) -> bool:
        return self.model.bidirectional

    @property
    def stride(self) -> int:
        """Frames per step of the model: the ``stride`` of the data it was trained on (its
        checkpoint's metadata, ``data.stride``); 1 for baselines and checkpoints without one."""
        return int((self.trained_metadata or {}).get("stride", 1))

    def first_frame(self) -> int:
        """The earliest frame a rollout can start from: its history, ``stride`` frames apart."""
        return self.stride * self.model.history

    def check_start(self, start: int) -> None:
        """Refuse a rollout start too early for the model's history (:class:`~rgns.errors.ConfigError`
        naming the method and the start it needs)."""
        if start < self.first_frame():
            raise ConfigError(f"start={start}: {self.label} ({self.source}) steps {self.stride} frames at a time with "
                              f"{self.model.history} velocities of history, so it needs start >= {self.first_frame()}")

    def forward_rollout(self, dataset, index: int, steps: int) -> Tensor:
        """Frames ``t0 + 1 .. t0 + steps`` of test trajectory ``index``, rolled out from its true
        state at ``t0 = dataset.start``; a strided model's in steps of ``stride`` frames, the
        frames between them filled in (:func:`~rgns.training.rollouts.forward_rollout`).  ``[steps, N, D]``"""
        self.check_start(dataset.start)
        position, particle_type = dataset.trajectories[index]
        return forward_rollout(self.model, position, particle_type, dataset.start, steps, self.stride)


def find_checkpoints(ckpt_path: str | None = None, ckpt_paths=(), checkpoints_dir: str | None = None,
                     checkpoint: str = "last", left_out: list[str] | None = None) -> list[Path]:
    """Checkpoint files: ``ckpt_path``, ``ckpt_paths`` and, under ``checkpoints_dir``, every
    ``checkpoints/last.ckpt`` (``checkpoint=last``) or newest ``checkpoints/best*.ckpt``
    (``checkpoint=best``), sorted by path. A run folder without the one asked for is named in a
    warning, and in ``left_out`` where given, and left out; when none has it, the error says
    what the folders hold."""
    if checkpoint not in ("last", "best"):
        raise ValueError(f"checkpoint={checkpoint!r}: 'last' (checkpoints/last.ckpt) or 'best' (the newest "
                         "checkpoints/best*.ckpt), for each run under checkpoints_dir")
    paths = [Path(p) for p in ([ckpt_path] if ckpt_path else []) + list(ckpt_paths or [])]
    if checkpoints_dir:
        if not Path(checkpoints_dir).is_dir():
            raise FileNotFoundError(f"checkpoints_dir={checkpoints_dir}: no such folder")
        pattern = "last.ckpt" if checkpoint == "last" else "best*.ckpt"
        folders = sorted({p.parent for p in Path(checkpoints_dir).rglob("checkpoints/*.ckpt")})
        if not folders:
            raise FileNotFoundError(f"{checkpoints_dir}: no checkpoints/*.ckpt under it")
        lacking = []
        for folder in folders:
            found = sorted(folder.glob(pattern), key=lambda p: p.stat().st_mtime)
            paths.extend(found[-1:])
            if not found:
                lacking.append(f"{folder} holds only {', '.join(sorted(p.name for p in folder.glob('*.ckpt')))}")
        other = "last" if checkpoint == "best" else "best"
        if len(lacking) == len(folders):
            raise FileNotFoundError(f"checkpoint={checkpoint}: no {pattern} under {checkpoints_dir}: "
                                    f"{'; '.join(lacking)}. Pass checkpoint={other} or ckpt_path=<one of those>")
        for item in lacking:
            log.warning("checkpoint=%s: no %s there, so that run is left out: %s", checkpoint, pattern, item)
            if left_out is not None:
                left_out.append(f"{item}, no {pattern} (checkpoint={checkpoint})")
    missing = [str(p) for p in paths if not p.is_file()]
    if missing:
        raise FileNotFoundError(f"checkpoint(s) not found: {', '.join(missing)}")
    if not paths:
        raise ValueError("no checkpoint given: set ckpt_path=..., ckpt_paths=[...] or checkpoints_dir=...")
    return list(dict.fromkeys(p.resolve() for p in paths))


def trained_on(source: str, data_root: str | None, relative: str | None) -> str | None:
    """The dataset folder the checkpoint ``source`` was trained on: ``data_root``, the absolute
    path it records, where that exists, else ``relative``, the path its run gave, from the
    current folder (a checkpoint trained in another checkout, e.g. ``pretrained/``). ``None``
    where it names none. Checkpoints that record no ``relative`` get ``data_root`` as it is.

    Raises :class:`~rgns.training.module.CheckpointError` naming the checkpoint and both paths
    when neither exists."""
    if relative is None or Path(data_root).exists():
        return data_root
    if Path(relative).exists():
        return str(Path(relative).resolve())
    raise CheckpointError(f"{source}: its dataset is neither at {data_root}, where it was trained, nor at "
                          f"{Path(relative).resolve()} ({relative}, as its run gave it, from the current folder); "
                          "pass the dataset folder (evaluate.py data_root=..., or --data-root)")


def check_fits(model: Simulator, source: str, metadata: dict, particle_types, where: str) -> None:
    """Refuse a trained model on data it cannot simulate: another dimension than it was trained
    in, or particle types it never saw in training (``model.particle_types``; unknown in
    checkpoints older than that record, then only the dimension is checked).

    Raises :class:`~rgns.training.module.CheckpointError` naming the checkpoint ``source``, the
    data ``where`` and what differs."""
    if int(metadata["dim"]) != model.dim:
        raise CheckpointError(f"{source}: trained on {model.dim}D data, but {where} is {metadata['dim']}D "
                              f"(metadata 'dim'): evaluate it on a {model.dim}D dataset")
    unseen = sorted(set(particle_types) - set(model.particle_types)) if model.particle_types is not None else []
    if unseen:
        raise CheckpointError(f"{source}: trained on particle types {model.particle_types}, but {where} also holds "
                              f"type(s) {unseen}, which it never saw in training")


def add_checkpoint_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments of a diagnostic of one checkpoint on one split (``python -m
    rgns.evaluation.rest``, ``onestep``, ``walls``): the checkpoint, ``--data-root`` (default:
    the dataset it was trained on), ``--split`` and ``--trajectories``; read by
    :func:`load_checkpoint_on_split`."""
    parser.add_argument("checkpoint")
    parser.add_argument("--data-root", default=None, help="default: the dataset the checkpoint was trained on")
    parser.add_argument("--split", default="test")
    parser.add_argument("--trajectories", type=int, default=8)


def load_checkpoint_on_split(args: argparse.Namespace):
    """``(model, root, dataset)``: the simulator of ``args.checkpoint``, the dataset folder
    (``args.data_root`` or the one it was trained on, :func:`trained_on`) and the first
    ``args.trajectories`` of its ``args.split``, checked to fit the model (:func:`check_fits`).
    The arguments are :func:`add_checkpoint_arguments`'s. A strided checkpoint (``data.stride``)
    is refused: the analysis tools step one frame at a time."""
    from rgns.evaluation.tasks import Dataset

    model, extras = load_simulator(args.checkpoint)
    stride = int(extras["hparams"]["metadata"].get("stride", 1))
    if stride > 1:  # these tools step a model one frame at a time
        raise ConfigError(f"{args.checkpoint}: steps {stride} frames at a time (data.stride={stride}); this tool "
                          "steps one frame at a time: evaluate it with evaluate.py task=forward or task=inverse")
    root = args.data_root or trained_on(args.checkpoint, extras["data_root"], extras.get("data_root_relative"))
    dataset = Dataset.load(root, args.split, args.trajectories, model.history, None)
    check_fits(model, args.checkpoint, dataset.metadata, dataset.particle_types, f"{root} ({args.split})")
    return model, root, dataset


def describe(model_config: dict) -> str:
    """``R-GNS 128x10``, ``R-GNS† 128x10`` (forward-only training), ablations and a basis other than
    the model's usual one appended (``GNS 128x10 differences basis``)."""
    cls = get_class(model_config["_target_"])
    name = getattr(cls, "display_name", "") or cls.__name__
    if model_config.get("train_inverse") is False:
        name += "†"
    label = f"{name} {model_config.get('latent', '?')}x{model_config.get('layers', '?')}"
    if model_config.get("encoder", "ilp") != "ilp":
        label += f" {model_config['encoder'].upper()} enc."
    if model_config.get("edges", "fixed") != "fixed":
        label += f" {model_config['edges']} edges"
    usual_basis = "differences" if issubclass(cls, RGNS) else "velocity"  # as conf/model/ sets it
    if model_config.get("basis", usual_basis) != usual_basis:
        label += f" {model_config['basis']} basis"
    if model_config.get("edge_velocity"):
        label += " edge velocity"
    if model_config.get("couplings", "node") != "node":
        label += f" {model_config['couplings']} couplings"
    if model_config.get("decoder", "node") != "node":
        label += f" {model_config['decoder']} decoder"
    return label


def _run_overrides(checkpoint: Path) -> list[str]:
    """The Hydra overrides of the training run that wrote ``checkpoint`` (``[]`` if unknown)."""
    overrides = checkpoint.parent.parent / ".hydra" / "overrides.yaml"
    return list(yaml.safe_load(overrides.read_text()) or []) if overrides.is_file() else []


def _disambiguate(methods: list[Method]) -> None:
    """Labels shared by several checkpoints get what differs between their runs: the Hydra
    overrides of a sweep (``loss=dl1``), else the run folder's name."""
    by_label: dict[str, list[Method]] = {}
    for method in methods:
        by_label.setdefault(method.label, []).append(method)
    for group in (g for g in by_label.values() if len(g) > 1):
        overrides = [set(m.info["overrides"]) for m in group]
        common = set.intersection(*overrides)
        for method, own in zip(group, overrides):
            extra = ",".join(o for o in method.info["overrides"] if o not in common and not o.startswith("hydra"))
            method.label += f" ({extra or Path(method.source).parent.parent.name})"
    labels = [m.label for m in methods]
    for i, method in enumerate(methods):  # still equal (same overrides): number them
        if labels.count(method.label) > 1:
            method.label += f" #{labels[:i].count(labels[i]) + 1}"


def _run_seed(checkpoint: Path) -> int | None:
    """The ``seed`` of the training run that wrote ``checkpoint`` (its ``.hydra/config.yaml``)."""
    config = checkpoint.parent.parent / ".hydra" / "config.yaml"
    return (yaml.safe_load(config.read_text()) or {}).get("seed") if config.is_file() else None


def load_checkpoints(paths: list[Path], device: str = "cpu", pretrained=(),
                     left_out: list[str] | None = None) -> list[Method]:
    """Methods of checkpoint files; those in ``pretrained`` are labelled ``<model> pretrained``.

    Of several files, one that cannot be read is named in a warning, and in ``left_out`` where
    given, and left out, and the others are loaded; a single file that cannot be read, or none
    of several, is an error (:class:`~rgns.training.module.CheckpointError`)."""
    methods, unreadable = [], []
    pretrained = {Path(p).resolve() for p in pretrained}
    for path in paths:
        try:
            model, extras = load_simulator(str(path), map_location=device)
        except CheckpointError as err:
            if len(paths) == 1:
                raise
            log.warning("%s. Left out of this evaluation; the other checkpoints are evaluated", err)
            unreadable.append(str(err))
            if left_out is not None:
                left_out.append(str(err))
            continue
        config = dict(extras["hparams"]["model"])
        is_pretrained = Path(path).resolve() in pretrained
        label = describe(config) + (" pretrained" if is_pretrained else "")
        methods.append(Method(label, model, extras["data_root"], str(path), dict(
            model=config, global_step=extras["global_step"], overrides=_run_overrides(path),
            seed=_run_seed(path), base_label=label, pretrained=is_pretrained), extras["data_root_relative"],
            extras["hparams"].get("metadata")))
    if paths and not methods:
        raise CheckpointError("no checkpoint could be read:\n" + "\n".join(unreadable))
    _disambiguate(methods)
    return methods


def seed_groups(methods: list[Method]) -> dict[str, list[str]]:
    """Labels of the runs that differ only by their seed, by what they share: ``{"R-GNS 32x2
    (3 seeds)": [label, ...]}``; groups of one are left out."""
    groups: dict[tuple, list[Method]] = {}
    for method in methods:
        if "base_label" not in method.info:
            continue
        same = tuple(sorted(o for o in method.info["overrides"] if not o.startswith(("seed=", "hydra"))))
        groups.setdefault((method.info["base_label"], same, method.data_root), []).append(method)
    return {f"{key[0]} ({len(group)} seeds)": [m.label for m in group]
            for key, group in groups.items() if len(group) > 1 and len({m.info["seed"] for m in group}) == len(group)}


def without_hard_walls(methods: list[Method]) -> list[Method]:
    """For each method whose model rolls out with hard walls (``model.hard_walls``), a twin on
    the same weights without them, labelled ``<label>, no hard walls``: what the network alone does."""
    twins = []
    for method in methods:
        if getattr(method.model, "hard_walls", False):
            model = copy.copy(method.model)  # shares the parameters; only the flag differs
            model.hard_walls = False
            twins.append(replace(method, label=f"{method.label}, no hard walls", model=model,
                                 info=dict(method.info, hard_walls=False)))
    return twins


def build_baselines(configs: dict | None, metadata: dict, history: int, device: str = "cpu") -> list[Method]:
    """``{name: {_target_: ..., ...}}`` -> training-free methods for one dataset, each labelled by its
    class's ``label`` (else its class name)."""
    methods = []
    for config in (configs or {}).values():
        # the metadata goes in as it is, past Hydra: its generator params hold configs with a _target_
        model = instantiate(config, _partial_=True)(metadata=metadata, history=history).to(device).eval()
        methods.append(Method(getattr(model, "label", type(model).__name__), model, None, "baseline"))
    return methods
