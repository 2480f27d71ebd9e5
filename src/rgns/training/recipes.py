"""Training through several steps: the pushforward trick and unrolled losses.

Both read the clean frames ``p^{t-k-lead} .. p^{t+horizon}`` that
:class:`~rgns.data.windows.WindowDataset` adds to a window when its ``lead`` or ``horizon`` is
set (``data.lead``, ``data.horizon``), and both are used by any model through
:class:`~rgns.training.module.SimulatorModule` (``module.pushforward``, ``module.unroll``).

- **Pushforward** (Brandstetter et al. 2022; the schedule of LagrangeBench): the model first runs
  ``u`` steps without gradients from frame ``t - u``, so the step it is trained on starts from a
  state of its own making, with the errors a rollout would have; ``u`` is drawn per batch from the
  entries of the schedule whose step has passed.
- **Unrolled loss** (as DMCF trains): the model runs ``n`` steps from frame ``t`` and the loss is
  the mean over the steps of the error of each predicted position, with gradients through every
  step; ``n`` grows on a schedule.

The state a recipe starts from carries the random-walk noise of a training window on its k
velocities, and the targets are the true positions shifted by the noise of the start frame (as
GNS shifts its target): the network corrects the noise in the velocities, not an offset of the
positions it cannot observe.
"""
from __future__ import annotations

import bisect
from typing import Sequence

import torch


class Pushforward:
    """How many steps a batch is pushed forward without gradients before its loss.

    Args:
        steps: global steps from which each entry may be drawn (an entry is drawn once
            ``global_step > steps[i]``); LagrangeBench: ``[-1, 20000, 300000, 400000]``.
        unrolls: steps pushed for each entry; LagrangeBench: ``[0, 1, 2, 3]``.
        probs: relative weights of the entries; LagrangeBench: ``[18, 2, 1, 1]``.
    """

    def __init__(self, steps: Sequence[int], unrolls: Sequence[int], probs: Sequence[float]):
        if not (len(steps) == len(unrolls) == len(probs)) or not steps:
            raise ValueError(f"pushforward: steps, unrolls and probs need the same length >= 1, got "
                             f"{list(steps)}, {list(unrolls)}, {list(probs)}")
        if any(u < 0 for u in unrolls) or any(p < 0 for p in probs) or list(steps) != sorted(steps):
            raise ValueError("pushforward: unrolls and probs must be >= 0 and steps increasing")
        self.steps, self.unrolls, self.probs = list(steps), list(unrolls), [float(p) for p in probs]

    @property
    def max_unrolls(self) -> int:
        return max(self.unrolls)

    def draw(self, global_step: int, generator: torch.Generator | None = None) -> int:
        """The number of pushed steps for a batch at ``global_step``."""
        available = bisect.bisect_left(self.steps, global_step)  # entries with steps[i] < global_step
        if available == 0:
            return 0
        weights = torch.tensor(self.probs[:available])
        if weights.sum() <= 0:
            return 0
        return self.unrolls[int(torch.multinomial(weights, 1, generator=generator))]


class Unroll:
    """How many steps an unrolled loss runs: ``lengths[i]`` from ``global_step >= steps[i]``.

    Args:
        steps: global steps at which the length changes, increasing, the first 0.
        lengths: steps unrolled from each of them (DMCF: 3 -> 5 -> 10 -> 20).
    """

    def __init__(self, steps: Sequence[int], lengths: Sequence[int]):
        if len(steps) != len(lengths) or not steps or list(steps) != sorted(steps) or min(lengths) < 1:
            raise ValueError(f"unroll: steps (increasing) and lengths (>= 1) of one length, got "
                             f"{list(steps)}, {list(lengths)}")
        self.steps, self.lengths = list(steps), list(lengths)

    @property
    def max_length(self) -> int:
        return max(self.lengths)

    def length(self, global_step: int) -> int:
        return self.lengths[max(bisect.bisect_right(self.steps, global_step) - 1, 0)]


__all__ = ["Pushforward", "Unroll"]
