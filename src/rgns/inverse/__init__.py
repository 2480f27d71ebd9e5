"""Inverse problems: recover an initial state from a target state K frames later.

- :mod:`rgns.inverse.optimise`: the optimisation-based inverse solver (Adam on the initial state
  through a differentiable simulator), its one stopping rule and its failure reports;
- :mod:`rgns.inverse.simulators`: the differentiable simulators it runs through (ballistic,
  differentiable SPH, a learned simulator); :mod:`rgns.inverse.mpm`: MLS-MPM water in torch;
- :mod:`rgns.inverse.feedforward`: feed-forward inverse inference (R-GNS / Sep-GNS) and the
  stability of long forward and inverse rollouts;
- :mod:`rgns.inverse.goal`: goal-conditioned shaping (text, mask or point targets);
- :mod:`rgns.inverse.tasks`: the inverse comparison (all methods, horizon sweep), as entry points
  for ``evaluate.py``.
"""
from rgns.inverse.optimise import InverseResult, StoppingRule, optimise_initial_state, state_loss

__all__ = ["InverseResult", "StoppingRule", "optimise_initial_state", "state_loss"]
