"""Sep-GNS: two separately trained GNS, one forward and one backward in time (the paper's
neural inverse baseline), behind the bidirectional simulator interface."""
from __future__ import annotations

import copy

from torch import Tensor

from rgns.models.base import Simulator, check_size
from rgns.models.gns import GNS


class SepGNS(Simulator):
    """A forward :class:`GNS` and a backward :class:`GNS` trained on time-reversed windows.

    Under time reversal velocities change sign and the order of the history flips, while
    accelerations keep theirs. The backward network therefore reads
    ``(-v^{t+1}, ..., -v^{t-k+2})`` (its "history", normalised with ``-vel_mean``) on the same
    graph of ``p^t`` as the forward one, and its "next velocity" is ``-v^{t-k+1}``.

    Args: as :class:`GNS`; both networks get the same sizes (``hard_walls`` acts on the steps of this model).
    """

    display_name = "Sep-GNS"
    bidirectional = True

    def __init__(self, metadata: dict, history: int = 5, noise_std: float = 6.7e-4, latent: int = 128,
                 layers: int = 10, hidden_layers: int = 2, embedding: int = 16, hard_walls: bool = False,
                 basis: str = "velocity", known_gravity: bool = False, edge_velocity: bool = False,
                 decoder: str = "node"):
        super().__init__(metadata, history, noise_std, embedding, hard_walls)
        check_size("model.latent", latent)
        check_size("model.layers", layers)
        del self.type_embedding  # each network owns its own
        reversed_metadata = copy.deepcopy(metadata)
        reversed_metadata["vel_mean"] = [-m for m in metadata["vel_mean"]]
        sizes = dict(history=history, noise_std=noise_std, latent=latent, layers=layers,
                     hidden_layers=hidden_layers, embedding=embedding, basis=basis,
                     known_gravity=known_gravity, edge_velocity=edge_velocity,
                     decoder=decoder)  # reversed time keeps gravity's sign (an acceleration)
        self.forward_gns = GNS(metadata, **sizes)
        self.backward_gns = GNS(reversed_metadata, **sizes)

    def next_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                      edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        return self.forward_gns.next_velocity(position, velocity_history, particle_type, edge_index, batch)

    def oldest_velocity(self, position: Tensor, velocity_history: Tensor, particle_type: Tensor,
                        edge_index: Tensor, batch: Tensor | None = None) -> Tensor:
        reversed_history = -velocity_history.flip(1)  # [N, k, D], newest (in reversed time) last
        return -self.backward_gns.next_velocity(position, reversed_history, particle_type, edge_index, batch)
