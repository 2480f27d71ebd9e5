"""Differentiable simulators behind one interface, for :func:`rgns.inverse.optimise.optimise_initial_state`.

Each has
``simulate(position [N, D], velocity, steps) -> (position [N, D], newest velocity [N, D])``,
differentiable in torch, and ``trajectory(position, velocity, steps) -> [steps + 1, N, D]``
(no gradients, for figures and consistency checks). Velocities are per frame (position units per
frame, dt = 1), as in the data contract; the physical solvers convert to m/s with their
``frame_dt``.

- :class:`Ballistic`: free flight under gravity, exact and cheap (tests; a known answer);
- :class:`SPHSimulator`: the differentiable WCSPH :class:`rgns.physics.sph.SPHSolver` (Taichi
  autodiff, one checkpoint per frame, so memory does not grow as K x N on the device) as a torch
  autograd function;
- :class:`LearnedSimulator`: K forward steps of a trained :class:`rgns.models.Simulator`
  (GNS, R-GNS, Sep-GNS); the initial "velocity" is the velocity history ``[N, k, D]``. The radius
  graph of each step is rebuilt from the current positions and held fixed (not differentiated);
  positions are differentiated through the edge features and wall distances. Each step is
  checkpointed (``torch.utils.checkpoint``), so activation memory is one step's, not K steps'.
- :class:`rgns.inverse.mpm.TorchMPM` (its own module): MLS-MPM water in torch autograd.
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor
from torch.utils.checkpoint import checkpoint

from rgns.models import Simulator, State


class Ballistic:
    """Particles in free flight: ``v^{t+1} = v^t + g``, ``p^{t+1} = p^t + v^{t+1}`` (per-frame units).

    Args:
        gravity: ``[D]`` acceleration per frame squared (e.g. ``g_SI * frame_dt**2``).
    """

    def __init__(self, gravity):
        self.gravity = torch.as_tensor(gravity, dtype=torch.float32)

    def simulate(self, position: Tensor, velocity: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        gravity = self.gravity.to(position)
        for _ in range(steps):
            velocity = velocity + gravity
            position = position + velocity
        return position, velocity

    @torch.no_grad()
    def trajectory(self, position: Tensor, velocity: Tensor, steps: int) -> Tensor:
        frames = [position]
        for _ in range(steps):
            position, velocity = self.simulate(position, velocity, 1)
            frames.append(position)
        return torch.stack(frames)


class _SPHFunction(torch.autograd.Function):
    """``(p^0, v^0) -> (p^K, v^K)`` through an :class:`~rgns.physics.sph.SPHSolver`, in SI units."""

    @staticmethod
    def forward(ctx, position: Tensor, velocity: Tensor, solver, steps: int):
        ctx.solver = solver
        final_position, final_velocity = solver.forward(position.detach().cpu().numpy(),
                                                        velocity.detach().cpu().numpy(), steps)
        return (torch.as_tensor(final_position, dtype=position.dtype, device=position.device),
                torch.as_tensor(final_velocity, dtype=position.dtype, device=position.device))

    @staticmethod
    def backward(ctx, grad_position: Tensor, grad_velocity: Tensor):
        grad_x, grad_v = ctx.solver.backward(grad_position.detach().cpu().numpy(),
                                             grad_velocity.detach().cpu().numpy())
        like = dict(dtype=grad_position.dtype, device=grad_position.device)
        return torch.as_tensor(grad_x, **like), torch.as_tensor(grad_v, **like), None, None


class SPHSimulator:
    """The differentiable WCSPH solver as a :class:`~rgns.inverse.optimise.DifferentiableSimulator`.

    Gradients come from :meth:`SPHSolver.backward` (replay of each frame from its checkpoint).
    Water only; a solve holds one solver, so calls must not interleave.

    Args:
        solver: an :class:`rgns.physics.sph.SPHSolver` whose ``frame_dt`` is the data's frame time.
    """

    def __init__(self, solver):
        self.solver = solver
        self.frame_dt = float(solver.frame_dt)

    def simulate(self, position: Tensor, velocity: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        final_position, final_velocity = _SPHFunction.apply(position, velocity / self.frame_dt, self.solver, steps)
        return final_position, final_velocity * self.frame_dt  # m/s -> per frame

    @torch.no_grad()
    def trajectory(self, position: Tensor, velocity: Tensor, steps: int) -> Tensor:
        frames = self.solver.rollout(position.detach().cpu().numpy(), (velocity / self.frame_dt).cpu().numpy(),
                                     num_frames=steps + 1)
        return torch.as_tensor(frames, dtype=position.dtype)


def sph_for_dataset(metadata: dict, capacity: int, substeps: int = 25, dtype: str = "f32"):
    """An :class:`SPHSolver` for a dataset: its box, frame time, gravity and particle spacing."""
    from rgns.physics.sph import SPHSolver

    dim = int(metadata["dim"])
    gravity = metadata.get("gravity") or ([0.0, -9.81] if dim == 2 else [0.0, -9.81, 0.0])
    return SPHSolver(dim=dim, capacity=capacity, bounds=metadata["bounds"], spacing=dataset_spacing(metadata),
                     frame_dt=float(metadata["dt"]), substeps=substeps, gravity=gravity, dtype=dtype)


def dataset_spacing(metadata: dict, frame: np.ndarray | None = None) -> float:
    """The particle spacing at rest of a dataset: ``generator.params.spacing`` from its metadata when
    it was generated here, else the median nearest-neighbour distance of ``frame [N, D]`` (a
    dataset frame, e.g. the first of a training trajectory)."""
    params = (metadata.get("generator") or {}).get("params") or {}
    if "spacing" in params:
        return float(params["spacing"])
    if frame is None:
        raise ValueError("the metadata carries no generator.params.spacing: pass a dataset frame to measure it")
    from scipy.spatial import cKDTree

    distance, _ = cKDTree(np.asarray(frame, dtype=np.float64)).query(frame, k=2)
    return float(np.median(distance[:, 1]))


@contextmanager
def _plain_backward(model: torch.nn.Module):
    """Switch off reversible layers' memory-saving backward (``memory_saving``) for the duration:
    it differentiates the latent, not the positions that enter through the conditions, and the
    per-step checkpoints already bound the memory."""
    saved = [(m, m.memory_saving) for m in model.modules() if hasattr(m, "memory_saving")]
    try:
        for m, _ in saved:
            m.memory_saving = False
        yield
    finally:
        for m, value in saved:
            m.memory_saving = value


class LearnedSimulator:
    """K forward steps of a learned simulator, differentiable in the initial position and velocity history.

    Args:
        model: a :class:`rgns.models.Simulator` (put in eval mode; its weights get no gradient:
            the optimiser differentiates the initial state only).
        particle_type: ``[N]``.
        checkpoint_steps: recompute each step in the backward pass instead of storing its activations.
    """

    def __init__(self, model: Simulator, particle_type: Tensor, checkpoint_steps: bool = True):
        self.model = model.eval()
        self.particle_type = particle_type
        self.checkpoint_steps = checkpoint_steps

    def velocity_shape(self, num_particles: int) -> tuple[int, int, int]:
        return (num_particles, self.model.history, self.model.dim)

    def _step(self, position: Tensor, velocity_history: Tensor) -> tuple[Tensor, Tensor]:
        with _plain_backward(self.model):  # here, so that a checkpoint's recomputation runs the same graph
            state = self.model.step(State(position, velocity_history, self.particle_type))
        return state.position, state.velocity_history

    def simulate(self, position: Tensor, velocity: Tensor, steps: int) -> tuple[Tensor, Tensor]:
        history = velocity  # [N, k, D]
        for _ in range(steps):
            if self.checkpoint_steps and torch.is_grad_enabled():
                position, history = checkpoint(self._step, position, history, use_reentrant=False)
            else:
                position, history = self._step(position, history)
        return position, history[:, -1]

    @torch.no_grad()
    def trajectory(self, position: Tensor, velocity: Tensor, steps: int) -> Tensor:
        state = State(position, velocity, self.particle_type)
        return torch.cat([position.unsqueeze(0), self.model.rollout(state, steps)]) if steps else position.unsqueeze(0)
