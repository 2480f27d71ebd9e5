"""What a stored config may build: the allow-list behind "a checkpoint is data, not code".

A checkpoint keeps the configs its model was built from (``hyper_parameters``: ``model``,
``loss``, ``optimizer``, ``scheduler``), and a generated dataset's ``metadata.json`` keeps its
scene's (``generator.params``). Hydra's ``instantiate`` calls whatever ``_target_`` such a config
names, so a shared file could name ``builtins.open`` or ``numpy.savetxt`` and write files on the
machine of whoever loads it. Before anything read from a file is instantiated (and before any
module it names is imported), :func:`check_stored_config` checks every ``_target_`` in it against
the role it plays:

=============  =========================================================================
role           allowed ``_target_``
=============  =========================================================================
``model``      a subclass of :class:`rgns.models.Simulator`, named under ``rgns.``
``loss``       :class:`rgns.training.losses.LossDesign` (or a subclass), under ``rgns.``
``optimizer``  a subclass of ``torch.optim.Optimizer``, named under ``torch.optim.``
``scheduler``  a subclass of ``torch.optim.lr_scheduler.LRScheduler``, under ``torch.optim.``
``scene``      a scene of :mod:`rgns.data.scenes`, its solver (:mod:`rgns.physics`) and shapes
=============  =========================================================================

Any other ``_target_``, one nested where none belongs, and any OmegaConf interpolation
(``${...}``: a resolver can run code too) is refused with :class:`UnsafeConfigError`, naming the
file and the key. Only modules under ``rgns.`` and ``torch.optim.`` are ever imported to check.
"""
from __future__ import annotations

import importlib
from typing import Any

_PREFIXES = {"model": ("rgns.",), "loss": ("rgns.",), "optimizer": ("torch.optim.",),
             "scheduler": ("torch.optim.lr_scheduler.",), "scene": ("rgns.data.scenes.", "rgns.physics."),
             "none": ()}  # "none": an entry rgns builds nothing from, where any _target_ is refused


class UnsafeConfigError(ValueError):
    """A stored config names something rgns does not build from files; the message names the
    file and the key."""


def _bases(role: str) -> tuple[type, ...]:
    if role == "model":
        from rgns.models import Simulator

        return (Simulator,)
    if role == "loss":
        from rgns.training.losses import LossDesign

        return (LossDesign,)
    if role == "optimizer":
        import torch

        return (torch.optim.Optimizer,)
    if role == "scheduler":
        import torch

        return (torch.optim.lr_scheduler.LRScheduler,)
    from rgns.data.scenes import Scene
    from rgns.physics.geometry import Capsule
    from rgns.physics.mpm import MPMSolver
    from rgns.physics.sph import SPHSolver

    return (Scene, MPMSolver, SPHSolver, Capsule)


def _locate(name: str) -> Any:
    """The object at the dotted ``name`` (a module, then attributes), or ``None``."""
    parts = name.split(".")
    for cut in range(len(parts) - 1, 0, -1):
        try:
            obj = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for attribute in parts[cut:]:
            obj = getattr(obj, attribute, None)
        return obj
    return None


def allowed_target(name: object, role: str) -> bool:
    """Whether ``name`` is a ``_target_`` a stored config of ``role`` may build. Modules are
    imported only when ``name`` lies under the role's packages (``rgns.``, ``torch.optim.``)."""
    if not isinstance(name, str) or not name.isascii() or not all(p.isidentifier() for p in name.split(".")):
        return False
    if not name.startswith(_PREFIXES[role]):
        return False
    obj = _locate(name)
    return isinstance(obj, type) and issubclass(obj, _bases(role))


def check_stored_config(config: Any, role: str, where: str) -> None:
    """Refuse ``config`` (plain dicts and lists, as read from a file) unless each ``_target_`` in
    it is one ``role`` allows: at its top for ``model``, ``loss``, ``optimizer`` and
    ``scheduler``; anywhere for ``scene`` (a scene nests its solver and shapes); nowhere for
    ``none``. ``where`` names
    the file and key in the error (``C: hyper_parameters.loss``).

    Raises :class:`UnsafeConfigError`."""
    for path, value in _walk(config, where):
        if isinstance(value, str) and "${" in value:
            raise UnsafeConfigError(f"{path}: holds an OmegaConf interpolation ({value[:80]!r}); a stored config is "
                                    "data, and interpolations can run resolvers: refused")
        if not isinstance(value, dict) or "_target_" not in value:
            continue
        nested = path != where
        if (nested and role != "scene") or not allowed_target(value["_target_"], role):
            what = ("in an entry rgns builds nothing from" if role == "none" else
                    "a nested _target_, which a stored config never needs" if nested and role != "scene" else
                    f"not one of rgns's own {role} classes")
            raise UnsafeConfigError(f"{path}._target_: {str(value['_target_'])[:120]!r} is {what}; refused (a "
                                    "checkpoint or dataset is data: rgns rebuilds only its own models, losses, "
                                    "optimisers, schedulers and scenes from it)")


def check_checkpoint_configs(hparams: dict, where: str) -> None:
    """Check every config a checkpoint's ``hyper_parameters`` hold (:func:`check_stored_config`):
    ``model``, ``loss``, ``optimizer`` and ``scheduler`` against their roles, the metadata's
    generator against the scene role, and no ``_target_`` anywhere else."""
    for key, value in hparams.items():
        here = f"{where}: hyper_parameters.{key}"
        if key in ("model", "loss", "optimizer", "scheduler"):
            if value is not None:
                check_stored_config(value, key, here)
        elif key == "metadata" and isinstance(value, dict):
            generator = value.get("generator")
            # no _target_ at all outside the generator's scene
            check_stored_config({k: v for k, v in value.items() if k != "generator"}, "none", here)
            if isinstance(generator, dict):
                check_stored_config(generator.get("params"), "scene", f"{here}.generator.params")
                check_stored_config({k: v for k, v in generator.items() if k != "params"}, "none", f"{here}.generator")
            else:
                check_stored_config(generator, "none", f"{here}.generator")
        else:
            check_stored_config(value, "none", here)


def _walk(config: Any, path: str):
    """``(path, value)`` of ``config`` and everything nested in it, depth first."""
    yield path, config
    if isinstance(config, dict):
        for key, value in config.items():
            if isinstance(value, (dict, list, tuple, str)):
                yield from _walk(value, f"{path}.{key}")
    elif isinstance(config, (list, tuple)):
        for i, value in enumerate(config):
            yield from _walk(value, f"{path}[{i}]")
