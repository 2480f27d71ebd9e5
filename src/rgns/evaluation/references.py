"""Solver references: a generated dataset's own ground-truth solver, re-run from the same initial
states, as yardsticks for the forward rollouts.

A generated dataset records how it was made (``metadata["generator"]``: the scene config
``params`` with its ``solver``, the ``seed``; see :mod:`rgns.data.generate`): trajectory ``i`` of
split ``s`` drew its initial state from ``numpy.random.default_rng([seed, s, i])`` through the
scene's ``sample`` (a subset of a split, :mod:`rgns.data.subset`, records each stored trajectory's
``i`` in ``generator.draws``). So the scene can be rebuilt, the initial state of each test trajectory drawn
again (checked against the stored frame 0), and the solver run again:

- at coarser resolutions (``resolutions``: fractions of the stored ``n_grid``, e.g. 0.5 and 0.75
  of 64 cells/m), with substeps in proportion to the grid as the CFL condition allows
  (``ceil(substeps * n_grid / stored n_grid)``, at least 1): a classical simulator and its cost,
  the front a learned model must beat;
- at the stored resolution from initial positions perturbed by Gaussian noise of std
  ``floor_perturbation`` metres (a fixed seed): the predictability floor, how far two solver runs
  that differ by that much drift apart.

A solver without a grid (SPH) cannot be coarsened in space: its resolution is the particle
spacing, which also sets the initial state, and the particles are what is compared. Its coarser
re-runs are coarser in time instead (:func:`sph_coarse_settings`): ``resolutions`` are fractions
of the stored substeps, the sound speed lowered in proportion so that the CFL limit
(``0.25 h / c``) holds as it did, and Monaghan's ``alpha`` raised in inverse proportion so that the
viscosity it models (``~ alpha c h``) stays the same: the same particles and equations, only
more compressible, as WCSPH is made cheaper in practice. At 1.0 the re-run is the stored one.
A dataset without a generator (converted from DeepMind's files) or whose scene cannot be rebuilt
gets none, with a sentence that says why.

Each reference runs the solver from frame 0 (Taichi on one CPU thread) and is compared on the
learned models' window, frames ``t0 + 1 .. t0 + steps``; kinematic particles (obstacles) take
their stored positions. Its cost is the wall time of the solver's rollout per frame (JIT warm-up
excluded). References are forward-only and have no parameters; to the evaluation tasks they are
methods with ``model = None`` (see :mod:`rgns.evaluation.methods`).
"""
from __future__ import annotations

import copy
import inspect
import math
import time

import numpy as np
import torch
from hydra.utils import get_class, instantiate
from torch import Tensor

from rgns.data.contract import KINEMATIC, SPLITS
from rgns.physics import runtime
from rgns.targets import check_stored_config


def metres(value: float) -> str:
    """``1e-4`` for 0.0001, ``2.5e-5`` for 0.000025: a length in a label."""
    mantissa, exponent = f"{value:.2e}".split("e")
    return f"{mantissa.rstrip('0').rstrip('.')}e{int(exponent)}"


def grid_substeps(n_grid: int, stored_n_grid: int, stored_substeps: int) -> int:
    """Substeps per frame for a grid of ``n_grid`` cells/m: the stored ones scaled with the grid
    (the CFL limit on the substep scales with the cell size), rounded up, at least 1."""
    return max(1, math.ceil(stored_substeps * n_grid / stored_n_grid - 1e-9))


def sph_coarse_settings(substeps: int, stored_substeps: int, sound_speed: float, viscosity: float) -> dict:
    """WCSPH with ``substeps`` per frame instead of ``stored_substeps``: the stored ``sound_speed``
    scaled by their ratio (the CFL limit on the substep, ``0.25 h / c``, holds as it did) and
    ``viscosity`` (Monaghan's alpha) by its inverse (``alpha c``, the viscosity it models, unchanged)."""
    return dict(substeps=substeps, sound_speed=sound_speed * substeps / stored_substeps,
                viscosity=viscosity * stored_substeps / substeps)


class SolverReference:
    """One re-run of a dataset's solver, a forward-only method of the evaluation.

    Args:
        label: its name in the tables ("MPM 32 cells/m", "MPM floor (1e-4 m)").
        scene: the dataset's scene, rebuilt with this reference's solver settings.
        initial_states: the redrawn initial state of each evaluated trajectory (``position``,
            ``velocity``, ``obstacles``, as :meth:`rgns.data.scenes.Scene.sample` gives them).
        settings: what it runs (solver, n_grid, substeps, perturbation, ...): ``results.json``.
        description: one sentence for the report.
        perturbation: std (m) of the Gaussian noise on the initial positions; ``None``: none.
        seed: the noise of trajectory ``i`` draws from ``default_rng([seed, i])``.
    """

    trained = False
    bidirectional = False
    parameters = 0
    model = None
    source = "reference"

    def __init__(self, label: str, scene, initial_states: list[dict], settings: dict, description: str,
                 perturbation: float | None = None, seed: int = 0):
        self.label, self.scene, self.initial_states = label, scene, initial_states
        self.settings, self.description = settings, description
        self.perturbation, self.seed = perturbation, seed
        self.info: dict = {}  # what results.json's methods list adds to the source
        self._runs: dict[int, tuple[np.ndarray, float]] = {}  # index -> (moving positions [F, n, D], seconds)
        self._warm = False

    def run(self, index: int, frames: int) -> np.ndarray:
        """Frames ``0 .. frames - 1`` of the moving particles of trajectory ``index``
        (``[frames, n, D]`` float32), timed; a longer run already made is reused."""
        if index in self._runs and len(self._runs[index][0]) >= frames:
            return self._runs[index][0][:frames]
        state = self.initial_states[index]
        position = state["position"]
        if self.perturbation:
            noise = np.random.default_rng([self.seed, index]).normal(scale=self.perturbation, size=position.shape)
            position = position + noise
        material = np.full(len(position), self.scene.material, np.int64)
        runtime.ensure_taichi()
        solver = self.scene.solver
        if not self._warm:  # Taichi compiles the kernels on their first call: not part of the cost
            solver.rollout(position, state["velocity"], material, 2, obstacles=state["obstacles"])
            self._warm = True
        begin = time.perf_counter()
        moving = solver.rollout(position, state["velocity"], material, frames, obstacles=state["obstacles"])
        self._runs[index] = (moving, time.perf_counter() - begin)
        return moving

    def trajectory(self, dataset, index: int, frames: int) -> Tensor:
        """The re-run trajectory ``[frames, N, D]``: the solver's moving particles, the stored
        kinematic ones (obstacles, exported after the moving particles)."""
        truth = dataset.trajectories[index][0]
        moving = self.run(index, frames)
        predicted = truth[:frames].clone()
        predicted[:, : moving.shape[1]] = torch.from_numpy(moving).to(truth)
        return predicted

    def forward_rollout(self, dataset, index: int, steps: int) -> Tensor:
        """Frames ``t0 + 1 .. t0 + steps`` of the re-run (from frame 0) trajectory ``index``.  ``[steps, N, D]``"""
        start = dataset.start
        return self.trajectory(dataset, index, start + 1 + steps)[start + 1 :]

    def ms_per_frame(self, index: int) -> float | None:
        if index not in self._runs:
            return None
        position, seconds = self._runs[index]
        return 1e3 * seconds / (len(position) - 1)

    def cost(self, dataset) -> dict:
        """The efficiency row: ms per frame of the solver's rollout of the first trajectory (the
        run of the forward rollouts, else a whole-trajectory run now); no parameters, memory not measured."""
        if 0 not in self._runs:
            self.run(0, len(dataset.trajectories[0][0]))
        return dict(parameters=0, weights_mb=0.0, forward_ms_per_step=self.ms_per_frame(0), forward_step_peak_mb=None,
                    forward_memory_mb=None, frames=len(self._runs[0][0]) - 1)

    def describe(self) -> dict:
        """What ``results.json`` records of this reference."""
        frames = {i: len(p) - 1 for i, (p, _) in sorted(self._runs.items())}
        taichi = dict(runtime._settings or {})  # arch and threads the solver ran with
        return dict(**self.settings, description=self.description, taichi=taichi,
                    frames_per_trajectory=frames, ms_per_frame_per_trajectory={i: self.ms_per_frame(i) for i in frames})


def rebuild_scene(metadata: dict, solver: dict | None = None, **scene):
    """The scene a generated dataset was made with, from ``metadata["generator"]["params"]``, with
    ``scene`` (e.g. ``capacity``) and ``solver`` (e.g. ``n_grid``, ``substeps``) changes applied.
    Raises ``ValueError`` with a sentence where the metadata records no generator (a dataset
    converted from DeepMind's files) and whatever the rebuild raises where it cannot be rebuilt."""
    generator = metadata.get("generator")
    if not isinstance(generator, dict) or not isinstance(generator.get("params"), dict):
        raise ValueError("the metadata records no generator (a dataset converted from DeepMind's files), so there "
                         "is no solver to re-run")
    params = copy.deepcopy(generator["params"])
    check_stored_config(params, "scene", "metadata: generator.params")  # data: only rgns's own scenes are built
    params.update(scene)
    params["solver"] = {**params["solver"], **(solver or {})}
    return instantiate(params)


class SolverReferences:
    """The ``references:`` block of ``conf/evaluate.yaml``: builds a dataset's solver references.

    Args:
        resolutions: grids to re-run at, as fractions of the stored ``n_grid`` (0.5 and 0.75 of
            64 cells/m: 32 and 48); for SPH, fractions of the stored substeps (0.5 and 0.75 of 20:
            10 and 15, see :func:`sph_coarse_settings`).
        floor_perturbation: std (m) of the noise on the initial positions of the floor's re-run
            at the stored resolution; ``None``: no floor.
        seed: of that noise.

    Called on a :class:`~rgns.evaluation.tasks.Dataset`, returns ``(references, note)``: the
    references, and a sentence for the report where some or all are absent (else ``None``).
    """

    def __init__(self, resolutions=(0.5, 0.75), floor_perturbation: float | None = 1e-4, seed: int = 0):
        self.resolutions, self.floor_perturbation, self.seed = list(resolutions or []), floor_perturbation, seed

    def settings(self) -> dict:
        return dict(resolutions=self.resolutions, floor_perturbation=self.floor_perturbation, seed=self.seed)

    def __call__(self, dataset) -> tuple[list[SolverReference], str | None]:
        generator = dataset.metadata.get("generator")
        if not isinstance(generator, dict) or not isinstance(generator.get("params"), dict):
            return [], ("No solver references: the metadata records no generator (a dataset converted from "
                        "DeepMind's files), so there is no solver to re-run.")
        params = copy.deepcopy(generator["params"])
        try:
            check_stored_config(params, "scene", f"{dataset.root}/metadata.json: generator.params")
            solver = dict(params["solver"])
            solver_class = get_class(solver["_target_"])
            scene = instantiate(params)
            draws = (generator.get("draws") or {}).get(dataset.split) or range(len(dataset.trajectories))
            initial_states = [scene.sample(np.random.default_rng([int(generator["seed"]), SPLITS.index(dataset.split), i]))
                              for i in list(draws)[:len(dataset.trajectories)]]
        except Exception as error:  # noqa: BLE001 - any failure to rebuild is reported, not raised
            return [], (f"No solver references: the generator's scene cannot be rebuilt "
                        f"({type(error).__name__}: {error}).")
        for i, (state, (position, particle_type)) in enumerate(zip(initial_states, dataset.trajectories)):
            first = position[0, particle_type != KINEMATIC].cpu().numpy()  # frame 0 of the moving particles
            if first.shape != state["position"].shape or not np.array_equal(first, state["position"].astype(np.float32)):
                return [], (f"No solver references: the initial state redrawn for {dataset.split} trajectory {i} is not "
                            f"the stored one (the generator has changed since the dataset was made: "
                            f"{generator.get('version')}).")

        defaults = {k: p.default for k, p in inspect.signature(solver_class).parameters.items()
                    if p.default is not inspect.Parameter.empty}
        stored = {**defaults, **solver}
        name = solver_class.__name__.removesuffix("Solver")
        common = dict(solver=solver["_target_"], split=dataset.split, generator_seed=int(generator["seed"]),
                      stored_n_grid=stored.get("n_grid"), stored_substeps=stored.get("substeps"))

        def rebuilt(**changes):
            return rebuild_scene(dataset.metadata, solver=changes)

        references, notes = [], []
        if "n_grid" in stored:
            for n_grid in dict.fromkeys(max(1, round(f * stored["n_grid"])) for f in self.resolutions):
                substeps = grid_substeps(n_grid, stored["n_grid"], stored["substeps"])
                references.append(SolverReference(
                    f"{name} {n_grid} cells/m", rebuilt(n_grid=n_grid, substeps=substeps), initial_states,
                    dict(common, n_grid=n_grid, substeps=substeps, perturbation=None),
                    f"the dataset's solver ({solver['_target_']}) re-run from the same initial states at {n_grid} "
                    f"cells/m with {substeps} substeps per frame (stored: {stored['n_grid']} cells/m, "
                    f"{stored['substeps']} substeps)."))
        elif {"substeps", "sound_speed", "viscosity"} <= set(stored):  # SPH: coarser in time
            for substeps in dict.fromkeys(max(1, math.ceil(f * stored["substeps"] - 1e-9)) for f in self.resolutions):
                coarse = sph_coarse_settings(substeps, stored["substeps"], stored["sound_speed"], stored["viscosity"])
                references.append(SolverReference(
                    f"{name} {coarse['substeps']} substeps", rebuilt(**coarse), initial_states,
                    dict(common, **coarse, perturbation=None),
                    f"the dataset's solver ({solver['_target_']}) re-run from the same initial states with "
                    f"{coarse['substeps']} substeps per frame, sound speed {coarse['sound_speed']:g} m/s and "
                    f"viscosity alpha {coarse['viscosity']:g} (stored: {stored['substeps']}, {stored['sound_speed']:g} "
                    f"m/s, {stored['viscosity']:g}): coarser in time, its particles those of the dataset, the CFL "
                    f"limit and the modelled viscosity as stored."))
        elif self.resolutions:
            notes.append(f"{name} has neither a grid nor substeps to coarsen: no coarser re-runs.")
        if self.floor_perturbation:
            references.append(SolverReference(
                f"{name} floor ({metres(self.floor_perturbation)} m)", scene, initial_states,
                dict(common, n_grid=stored.get("n_grid"), substeps=stored.get("substeps"),
                     perturbation=self.floor_perturbation, perturbation_seed=self.seed),
                f"the predictability floor: the dataset's solver at its stored resolution, re-run from the initial "
                f"positions perturbed by Gaussian noise of std {metres(self.floor_perturbation)} m (seed {self.seed}).",
                perturbation=self.floor_perturbation, seed=self.seed))
        return references, " ".join(notes) or None
