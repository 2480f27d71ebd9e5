"""Run folders that no two runs share.

``hydra.run.dir: ${rgns_fresh:runs/${now:%Y-%m-%d_%H-%M-%S}}`` names a run by the second it
started, like Hydra's default, and claims the folder by creating it: ``os.mkdir`` fails for every
process but one, so a second run started in the same second (a script launching several, a
scheduler's array job) takes ``<name>_2``, the next ``<name>_3``, and so on. The claim is made
once per process and name, so every copy of the config a process resolves points to one folder.
An explicit ``hydra.run.dir=...`` is used as given.

``train.py`` and ``evaluate.py`` register the resolver before Hydra composes their config; an
application composing ``rgns.conf`` with its Hydra settings calls :func:`register_resolvers` first.
"""
from __future__ import annotations

import os
from pathlib import Path

from omegaconf import OmegaConf

_claimed: dict[str, str] = {}


def claim_run_dir(base: str) -> str:
    """``base``, or ``base_2``, ``base_3``...: the first that this call could create."""
    if base not in _claimed:
        Path(base).parent.mkdir(parents=True, exist_ok=True)
        for n in range(1, 10_000):
            candidate = base if n == 1 else f"{base}_{n}"
            try:
                os.mkdir(candidate)
            except FileExistsError:
                continue
            _claimed[base] = candidate
            break
        else:
            raise RuntimeError(f"could not claim a run folder: {base} and 9,999 numbered variants exist")
    return _claimed[base]


def register_resolvers() -> None:
    """Register ``${rgns_fresh:...}`` (:func:`claim_run_dir`) with OmegaConf, once."""
    if not OmegaConf.has_resolver("rgns_fresh"):
        OmegaConf.register_new_resolver("rgns_fresh", claim_run_dir)
