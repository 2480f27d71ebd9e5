"""What every rgns simulator shares: the physical state, normalisation, node conditions and
the rollout loops.

The data contract of a simulator, stated once:

- State at frame t: positions ``p^t [N, D]``, velocity history
  ``V^t = (v^{t-k+1}, ..., v^t) [N, k, D]``, particle types ``[N]`` (DeepMind's ids), optional
  PyG ``batch [N]``. Velocities are position differences per frame (dt = 1), physical units.
- Forward: ``v^{t+1} = next_velocity(p^t, V^t)``; ``p^{t+1} = p^t + v^{t+1}``;
  ``V^{t+1} = (v^{t-k+2}, ..., v^{t+1})``.
- Inverse (bidirectional models): from ``(p^{t+1}, V^{t+1})``, ``p^t = p^{t+1} - v^{t+1}`` is
  exact; ``v^{t-k+1} = oldest_velocity(p^t, V^{t+1})`` is predicted;
  ``V^t = (v^{t-k+1}, ..., v^t)``.
- Both directions of the step t <-> t+1 read the same graph: the radius graph of ``p^t``.
- Kinematic particles (type 3) are conditions: their predicted velocities are replaced by the
  ones that take them to their known positions (or keep them where they are).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, replace

import torch
from torch import Tensor, nn

from rgns.data.contract import KINEMATIC, NUM_PARTICLE_TYPES
from rgns.data.graph import NeighbourList, batched_radius_graph, wall_distance
from rgns.errors import ConfigError

log = logging.getLogger(__name__)


@dataclass
class State:
    """The physical state of a particle system at frame t."""

    position: Tensor  # [N, D], p^t
    velocity_history: Tensor  # [N, k, D], v^{t-k+1} .. v^t
    particle_type: Tensor  # [N] int64
    batch: Tensor | None = None  # [N] graph id per particle, sorted

    @classmethod
    def from_positions(cls, positions: Tensor, particle_type: Tensor, batch: Tensor | None = None) -> "State":
        """Build the state at the last of ``k + 1`` frames.

        Shapes:
            positions: ``[k + 1, N, D]``  ->  position ``[N, D]``, velocity_history ``[N, k, D]``
        """
        velocity = positions[1:] - positions[:-1]  # [k, N, D]
        return cls(positions[-1], velocity.transpose(0, 1).contiguous(), particle_type, batch)

    def to(self, device: torch.device | str) -> "State":
        return State(*(None if t is None else t.to(device)
                       for t in (self.position, self.velocity_history, self.particle_type, self.batch)))


def check_size(key: str, value, minimum: int = 1, even: bool = False) -> None:
    """Refuse a size option (``model.layers``, ``model.latent``) that is not an integer of at
    least ``minimum`` (and even, where ``even``), naming the key: ``model.layers=two`` or
    ``model.latent=3`` for R-GNS would otherwise fail deep inside the first layer built."""
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ConfigError(f"{key}={value!r}: must be an integer of at least {minimum}")
    if even and value % 2:
        raise ConfigError(f"{key}={value}: R-GNS splits the latent into two halves, so it must be even")


class Simulator(nn.Module):
    """Base of the simulators: normalisation buffers from ``metadata`` and the physical loops.

    Subclasses implement :meth:`next_velocity` and, if ``bidirectional``, :meth:`oldest_velocity`.

    Args:
        metadata (dict): the dataset's ``metadata.json`` (``bounds``, ``dim``,
            ``default_connectivity_radius``, ``vel_mean``, ``vel_std``, ``acc_mean``, ``acc_std``),
            and optionally ``particle_types``, those of the training data (the datamodule adds
            them): kept as :attr:`particle_types` (``None``: unknown) so that data with types the
            model never saw can be refused.
        history (int, optional): velocities per state, k. (default: :obj:`5`)
        noise_std (float, optional): training noise, added in quadrature to the stds as in GNS.
            (default: :obj:`6.7e-4`)
        embedding (int, optional): width of the particle-type embedding. (default: :obj:`16`)
        hard_walls (bool, optional): a hard wall in :meth:`step` and :meth:`inverse_step`: a
            particle the network would move out of the box ``bounds`` stops at the wall (its
            position is clamped into the box and the step's velocity is the displacement that got
            it there, so ``p^{t+1} = p^t + v^{t+1}`` still holds and the normal velocity into the
            wall is zero). Training targets are untouched; only rollouts see the wall. Near a wall
            it breaks the exact inverse of the network for the particles it stops.
            (default: :obj:`False`)

    :attr:`wall_gradient` says how gradients cross that wall in the steps of a multi-step loss:
    ``"stop"`` (the clamp's own: none along a clamped coordinate, so a rollout that pushes water
    into the floor is not told so) or ``"through"`` (straight-through: the step's value is the
    clamped one, its gradient the unclamped step's). Rollouts without gradients are the same
    either way. The training module sets it (``wall_gradient`` in ``conf/train.yaml``).
    """

    wall_gradient: str = "stop"
    # rollouts keep the pairs within (1 + neighbour_skin) R between steps (NeighbourList); 0: a fresh
    # radius graph per step, the faster on WaterDrop, whose splash outruns a skin (docs/benchmarks.md)
    neighbour_skin: float = 0.0
    precision: str = "float32"  # "bfloat16": the network's matrix products in bfloat16 (low_precision; opt-in)

    bidirectional: bool = False
    display_name: str = ""  # the name reports give the model (``describe``); empty: the class name
    collapse_factor: float | None = 30.0  # rollouts stop past this x the initial densest R-cell (``rollout``)

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, embedding: int = 16,
                 hard_walls: bool = False):
        super().__init__()
        check_size("history", history)
        self.history = history
        self.hard_walls = bool(hard_walls)
        self.dim = int(metadata["dim"])
        self.radius = float(metadata["default_connectivity_radius"])
        self.particle_types = metadata.get("particle_types")  # of the training data; None: unknown

        def stat(key: str) -> Tensor:
            return torch.as_tensor(metadata[key], dtype=torch.float32)

        self.register_buffer("bounds", stat("bounds"))  # [D, 2]
        self.register_buffer("vel_mean", stat("vel_mean"))  # [D]
        self.register_buffer("vel_std_noisy", (stat("vel_std") ** 2 + noise_std**2).sqrt())
        self.register_buffer("acc_mean", stat("acc_mean"))
        self.register_buffer("acc_std_noisy", (stat("acc_std") ** 2 + noise_std**2).sqrt())
        self.type_embedding = nn.Embedding(NUM_PARTICLE_TYPES, embedding)
        for key, std in (("vel_std", self.vel_std_noisy), ("acc_std", self.acc_std_noisy)):
            if not bool((std > 0).all()):  # every normalised input or target would divide by zero
                raise ConfigError(f"metadata '{key}' is {metadata[key]} and noise_std={noise_std}: velocities and "
                                  f"accelerations are divided by sqrt({key}^2 + noise_std^2), which is 0 here; the "
                                  f"dataset's particles do not move, or its '{key}' is wrong (or set noise_std > 0)")

    def low_precision(self) -> torch.autocast:
        """The context the network's matrix products run in: ``torch.autocast`` to bfloat16 where
        :attr:`precision` is ``"bfloat16"``, disabled for ``"float32"`` (the default). An option
        for rollouts on CPUs with AMX or AVX512-BF16, whose bfloat16 products are several times
        faster; its rounding (2^-9) reaches the predicted accelerations, which pair terms get as
        differences of two evaluations: what it buys and costs is measured in docs/benchmarks.md.
        The models keep out of it what must stay exact: R-GNS its encoder, decoder and latent
        stream, every model the integration of the positions."""
        if self.precision not in ("float32", "bfloat16"):
            raise ConfigError(f"precision={self.precision!r}: must be 'float32' or 'bfloat16'")
        return torch.autocast(self.bounds.device.type, dtype=torch.bfloat16, enabled=self.precision == "bfloat16")

    @property
    def condition_channels(self) -> int:
        """Width of :meth:`node_conditions`: type embedding and two wall distances per axis."""
        return self.type_embedding.embedding_dim + 2 * self.dim

    def warm_start_optional(self) -> set[str]:
        """Names of parameters (as in :meth:`state_dict`) that a warm start (``init_from``) may
        find missing in its checkpoint: those of an option that starts as a no-op (zero
        initialised), so the network with the checkpoint's weights computes what it computed."""
        return set()

    def warm_start_added(self, present: set[str]) -> set[str]:
        """Names of parameters (as in :meth:`state_dict`) that a warm start with ``init_grow``
        may find missing in a checkpoint holding ``present``: those of layers this model has past
        the checkpoint's, when they start as the identity, so the deeper network with the
        checkpoint's weights computes what the shallower one computed. None here: only a model
        whose added layers start as the identity can grow."""
        return set()

    def node_conditions(self, position: Tensor, particle_type: Tensor) -> Tensor:
        """Static node inputs: distance to the walls over R, clipped to [-1, 1], and the type embedding.

        Shapes:
            position: ``[N, D]``, particle_type: ``[N]``  ->  ``[N, 2 D + embedding]``
        """
        walls = wall_distance(position, self.bounds, self.radius)  # [N, 2D]
        return torch.cat([walls, self.type_embedding(particle_type)], dim=-1)

    def normalise_velocity(self, velocity: Tensor) -> Tensor:
        return (velocity - self.vel_mean) / self.vel_std_noisy

    def denormalise_velocity(self, velocity: Tensor) -> Tensor:
        return velocity * self.vel_std_noisy + self.vel_mean

    def to_differences(self, velocity_history: Tensor, anchor: int) -> Tensor:
        """A fixed invertible change of basis of ``V [N, k, D]`` around the slot ``anchor``:
        ``v^anchor`` normalised by the velocity statistics, every other slot as its difference to
        the neighbour towards ``anchor`` (newer slots ``v^j - v^{j-1}``, older ``v^{j+1} - v^j``)
        over the acceleration std. A network reading it sees accelerations at their own scale,
        not as small differences of normalised velocities (about 14x larger on the default data).

        Shapes:
            velocity_history: ``[N, k, D]``  ->  ``[N, k, D]``
        """
        c = anchor
        centre = self.normalise_velocity(velocity_history[:, c : c + 1])  # [N, 1, D]
        newer = (velocity_history[:, c + 1 :] - velocity_history[:, c:-1]) / self.acc_std_noisy
        older = (velocity_history[:, 1 : c + 1] - velocity_history[:, :c]) / self.acc_std_noisy
        return torch.cat([older, centre, newer], dim=1)

    def from_differences(self, x: Tensor, anchor: int) -> Tensor:
        """The inverse of :meth:`to_differences`: ``[N, k, D]`` -> physical ``V [N, k, D]``."""
        c = anchor
        centre = self.denormalise_velocity(x[:, c : c + 1])  # [N, 1, D]
        newer = centre + (x[:, c + 1 :] * self.acc_std_noisy).cumsum(1)  # v^{c+1} .. v^{k-1}
        older = centre - (x[:, :c] * self.acc_std_noisy).flip(1).cumsum(1).flip(1)  # v^0 .. v^{c-1}
        return torch.cat([older, centre, newer], dim=1)

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        """Predict ``v^{t+1} [N, D]`` from ``p^t [N, D]`` and ``V^t [N, k, D]`` on the radius graph of ``p^t``."""
        raise NotImplementedError

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        """Predict ``v^{t-k+1} [N, D]`` from ``p^t [N, D]`` and ``V^{t+1} [N, k, D]`` on the radius graph of ``p^t``."""
        raise NotImplementedError(f"{type(self).__name__} simulates forward in time only")

    def both_velocities(self, position: Tensor, forward_history: Tensor, inverse_history: Tensor,
                        particle_type: Tensor, edge_index: Tensor, batch: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(next_velocity(.., V^t ..), oldest_velocity(.., V^{t+1} ..))`` on one graph: the two
        predictions of a bidirectional training step. Models whose directions share work override it."""
        return (self.next_velocity(position, forward_history, particle_type, edge_index, batch),
                self.oldest_velocity(position, inverse_history, particle_type, edge_index, batch))

    # ---- compiled networks ---------------------------------------------------------------------

    NETWORK_FUNCTIONS = ("next_velocity", "oldest_velocity", "both_velocities")

    def compile_network(self, **options) -> None:
        """Run the network functions (:attr:`NETWORK_FUNCTIONS`: one call per direction, or both
        at once) through ``torch.compile(fn, **options)`` from now on, e.g. ``dynamic=True`` for
        graphs whose sizes change every batch. The fused kernels cut the per-operation overhead
        that dominates a small model's step on a CPU (docs/benchmarks.md). The first calls of
        each kind (training, no-grad rollouts, single or batched graphs) pay the compilation.

        Only this instance changes: weights, ``state_dict`` and checkpoints are the same as
        eager, and a copy (``copy.deepcopy``, pickling; e.g. an averaged model) runs eager."""
        for name in self.NETWORK_FUNCTIONS:
            self.__dict__[name] = torch.compile(getattr(type(self), name).__get__(self), **options)

    @property
    def compiled(self) -> bool:
        """Whether :meth:`compile_network` wraps this instance's network functions."""
        return any(name in self.__dict__ for name in self.NETWORK_FUNCTIONS)

    def __getstate__(self) -> dict:  # copies and pickles leave the compiled wrappers behind
        return {key: value for key, value in self.__dict__.items() if key not in self.NETWORK_FUNCTIONS}

    # ---- the physical loops -------------------------------------------------------------------

    def stop_at_walls(self, position: Tensor, velocity: Tensor) -> Tensor:
        """The velocity that takes ``position`` to ``position + velocity`` clamped into the box,
        with the gradient :attr:`wall_gradient` says. ``[N, D]``"""
        stopped = (position + velocity).clamp(self.bounds[:, 0], self.bounds[:, 1]) - position
        if self.wall_gradient == "through":
            return velocity + (stopped - velocity).detach()
        return stopped

    def graph(self, position: Tensor, batch: Tensor | None = None) -> Tensor:
        """Radius graph of ``position`` (scipy on the CPU), on the model's device.  ``[2, E]``"""
        return batched_radius_graph(position, self.radius, batch).to(position.device)

    def step(self, state: State, kinematic_position: Tensor | None = None,
             neighbours: NeighbourList | None = None) -> State:
        """Advance one frame: ``(p^t, V^t) -> (p^{t+1}, V^{t+1})``.

        ``kinematic_position [N, D]``: positions of frame t+1 imposed on kinematic particles
        (others' rows are ignored); ``None`` keeps them where they are. ``neighbours``: the
        neighbour list a rollout keeps between steps (the same edges as :meth:`graph`).
        """
        position, history = state.position, state.velocity_history
        edge_index = self.graph(position, state.batch) if neighbours is None else neighbours(position, state.batch)
        velocity = self.next_velocity(position, history, state.particle_type, edge_index, state.batch)  # [N, D]
        if self.hard_walls:
            velocity = self.stop_at_walls(position, velocity)
        kinematic = (state.particle_type == KINEMATIC).unsqueeze(-1)
        imposed = torch.zeros_like(position) if kinematic_position is None else kinematic_position - position
        velocity = torch.where(kinematic, imposed, velocity)
        history = torch.cat([history[:, 1:], velocity.unsqueeze(1)], dim=1)  # [N, k, D]
        return replace(state, position=position + velocity, velocity_history=history)  # dt = 1

    def inverse_step(self, state: State, kinematic_position: Tensor | None = None,
                     neighbours: NeighbourList | None = None) -> State:
        """Go back one frame: ``(p^{t+1}, V^{t+1}) -> (p^t, V^t)``.

        ``p^t = p^{t+1} - v^{t+1}`` is exact; the network predicts the oldest velocity
        ``v^{t-k+1}``, which fixes the position of frame ``t-k``
        (``p^{t-k} = p^{t+1} - sum(V^{t+1}) - v^{t-k+1}``). ``kinematic_position [N, D]`` are the
        kinematic particles' positions at that frame, ``t-k``; ``None`` keeps them still there.
        ``neighbours``: as in :meth:`step`.
        """
        history = state.velocity_history
        position = state.position - history[:, -1]  # p^t, exact
        edge_index = self.graph(position, state.batch) if neighbours is None else neighbours(position, state.batch)
        velocity = self.oldest_velocity(position, history, state.particle_type, edge_index, state.batch)  # [N, D]
        if self.hard_walls:  # the frame it fixes, p^{t-k} = p^{t-k+1} - v^{t-k+1}, stays in the box
            earliest = state.position - history.sum(dim=1)  # p^{t-k+1}
            velocity = -self.stop_at_walls(earliest, -velocity)
        kinematic = (state.particle_type == KINEMATIC).unsqueeze(-1)
        if kinematic_position is None:
            imposed = torch.zeros_like(position)
        else:
            imposed = (state.position - history.sum(dim=1)) - kinematic_position  # p^{t-k+1} - p^{t-k}
        velocity = torch.where(kinematic, imposed, velocity)
        history = torch.cat([velocity.unsqueeze(1), history[:, :-1]], dim=1)  # [N, k, D]
        return replace(state, position=position, velocity_history=history)

    def densest_cell(self, position: Tensor, batch: Tensor | None = None) -> int:
        """The most particles in one cell of a grid of side R (per graph of a batch): a state
        whose particles clumped has a dense radius graph, which makes every further step
        quadratic in the clump's size."""
        cell = torch.floor((position - self.bounds[:, 0]) / self.radius).clamp(-1e4, 1e4).long()  # [N, D]
        cell = cell - cell.min(dim=0).values
        key = torch.zeros(len(position), dtype=torch.long, device=position.device)
        for axis in range(self.dim):
            key = key * (int(cell[:, axis].max()) + 1) + cell[:, axis]
        if batch is not None:
            key = key + batch * (int(key.max()) + 1)
        return int(torch.unique(key, return_counts=True)[1].max())

    @torch.no_grad()
    def rollout(self, state: State, steps: int, kinematic_positions: Tensor | None = None) -> Tensor:
        """Positions of frames t+1 .. t+steps.  ``kinematic_positions [steps, N, D]`` -> ``[steps, N, D]``

        A rollout whose densest cell of side R holds more than :attr:`collapse_factor` times the
        initial state's densest has collapsed, far
        past any fluid's compression or a pile against a wall: it stops there, logs it, and repeats
        its last frame for the remaining steps, so its error stays counted while a clump's
        quadratic radius graph no longer costs minutes per step. ``collapse_factor = None``: never stop.
        A rollout whose positions turn non-finite stops there too, its remaining frames NaN (no radius
        graph can be built of them): its error is not finite and its break "non-finite", not a crash.

        The radius graphs come from one :class:`~rgns.data.graph.NeighbourList` with a skin of
        :attr:`neighbour_skin` times R: the same edges as a fresh graph per step (found again
        only when some particle has moved half the skin; with the default 0, every step).
        """
        return self._unroll(self.step, state, steps, kinematic_positions, 0, "rollout")[0]

    @torch.no_grad()
    def inverse_rollout(self, state: State, steps: int, kinematic_positions: Tensor | None = None,
                        return_state: bool = False) -> Tensor | tuple[Tensor, State]:
        """Positions of frames t-1, t-2, .., t-steps (going back in time), stopped as :meth:`rollout`
        stops where it collapses or turns non-finite.

        ``kinematic_positions [M, N, D]``: kinematic positions of frames t-1, t-2, .. (row i is frame
        t-1-i; frames past row M - 1 keep what the model infers); frames t-1 .. t-k follow from the
        state's own velocity history, so step i places them at row i + k. ``return_state``: also the
        state the rollout ended in (where it stopped, if it stopped), to run forward again from.
        """
        if not self.bidirectional:
            raise NotImplementedError(f"{type(self).__name__} simulates forward in time only")
        positions, state = self._unroll(self.inverse_step, state, steps, kinematic_positions, self.history,
                                        "inverse rollout")
        return (positions, state) if return_state else positions

    def _unroll(self, step, state: State, steps: int, kinematic_positions: Tensor | None, lag: int,
                name: str) -> tuple[Tensor, State]:
        """``steps`` applications of ``step(state, known, neighbours)``; ``known``: row ``i + lag`` of
        ``kinematic_positions`` at step i where there is one. Stops at a collapse (repeats the last
        frame) or a non-finite state (NaN from there). The positions ``[steps, N, D]`` and the last
        state stepped to."""
        factor = self.collapse_factor
        limit = None if factor is None else factor * self.densest_cell(state.position, state.batch)
        neighbours = NeighbourList(self.radius, self.neighbour_skin * self.radius)
        known_rows = 0 if kinematic_positions is None else len(kinematic_positions)
        positions = []
        for i in range(steps):
            state = step(state, kinematic_positions[i + lag] if i + lag < known_rows else None, neighbours)
            positions.append(state.position)
            if i + 1 == steps:
                break
            # the next step's graph is built on p^t (forward) or p^t - v^t (backward): finite only if both are
            if not bool(torch.isfinite(state.position - state.velocity_history[:, -1]).all()):
                log.warning("%s %s non-finite at step %d of %d: NaN from there", type(self).__name__, name,
                            i + 1, steps)
                positions.extend([torch.full_like(state.position, float("nan"))] * (steps - i - 1))
                break
            if limit is not None and self.densest_cell(state.position, state.batch) > limit:
                log.warning("%s %s collapsed at step %d of %d (more than %.0f particles in one cell "
                            "of side R): the remaining frames repeat its last", type(self).__name__, name, i + 1,
                            steps, limit)
                positions.extend([state.position] * (steps - i - 1))
                break
        return torch.stack(positions), state

    def extra_repr(self) -> str:
        return f"dim={self.dim}, history={self.history}, radius={self.radius:g}, hard_walls={self.hard_walls}"


def dataset_gravity(metadata: dict, gravity: list[float] | None = None) -> Tensor:
    """The external force per unit mass in position units per frame squared. ``[D]``

    ``gravity`` (m/s^2, given) or ``metadata["gravity"]`` (the generated datasets'), times
    ``dt^2``; data that carries neither (DeepMind's) has its mean acceleration ``acc_mean`` stand
    in, as for the ballistic baseline (rgns.evaluation.baselines).
    """
    if gravity is None:
        gravity = metadata.get("gravity")
    if gravity is None:
        return torch.as_tensor(metadata["acc_mean"], dtype=torch.float32)
    gravity = torch.as_tensor(gravity, dtype=torch.float32)
    if gravity.shape != (int(metadata["dim"]),):
        raise ValueError(f"gravity {gravity.tolist()} needs {metadata['dim']} components")
    return gravity * float(metadata["dt"]) ** 2


def count_parameters(module: nn.Module) -> int:
    return sum(p.numel() for p in module.parameters() if p.requires_grad)


__all__ = ["State", "Simulator", "count_parameters", "dataset_gravity"]
