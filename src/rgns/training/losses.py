"""The loss designs of the paper's ablation: DL_1 = MSE + MMD, DL_2 = MSE + cosine + MMD,
DL_3 = MSE + cosine, DL_4 = MSE. Weights come from ``conf/loss/dl*.yaml``.

All terms act on the normalised *change* a prediction makes to its known neighbour in the
history (the newest velocity minus ``v^t`` forward, the oldest minus ``v^{t-k+2}`` inverse):
velocities themselves are nearly parallel frame to frame, so cosine and MMD on them would say
little. The MSE of that change equals the MSE of the velocity, normalised by the
acceleration std.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from rgns.data.graph import kernel_density


def gaussian_mmd(x: torch.Tensor, y: torch.Tensor, bandwidths: tuple[float, ...] = (0.5, 1.0, 2.0)) -> torch.Tensor:
    """Squared maximum mean discrepancy between samples x ``[n, d]`` and y ``[m, d]``,
    with a sum of Gaussian kernels (biased V-statistic, zero for identical sets)."""
    xy = torch.cat([x, y])
    distance = torch.cdist(xy, xy).pow(2)
    kernel = sum(torch.exp(-distance / (2 * h**2)) for h in bandwidths)
    n = len(x)
    return kernel[:n, :n].mean() + kernel[n:, n:].mean() - 2 * kernel[:n, n:].mean()


@dataclass
class LossDesign:
    """Weighted sum of MSE, cosine dissimilarity and MMD.

    Args:
        name: label in logs (``DL1`` ... ``DL4``).
        mse, cosine, mmd: weights of the three terms.
        mmd_points: particles sampled per graph for the MMD (its cost is quadratic).
    """

    name: str = "DL4"
    mse: float = 1.0
    cosine: float = 0.0
    mmd: float = 0.0
    mmd_points: int = 256

    def __call__(self, change: torch.Tensor, target_change: torch.Tensor, batch: torch.Tensor) -> dict[str, torch.Tensor]:
        """Loss terms on normalised changes ``[N, D]`` of the moving particles, ``batch [N]`` their graph."""
        terms = {"mse": F.mse_loss(change, target_change)}
        if self.cosine:
            terms["cosine"] = (1 - F.cosine_similarity(change, target_change, dim=-1, eps=1e-6)).mean()
        if self.mmd:
            graphs = [batch == g for g in batch.unique()]
            terms["mmd"] = torch.stack(
                [gaussian_mmd(*self._sample(change[m], target_change[m])) for m in graphs]
            ).mean()
        terms["loss"] = sum(getattr(self, key) * value for key, value in terms.items())
        return terms

    def _sample(self, x: torch.Tensor, y: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if len(x) <= self.mmd_points:
            return x, y
        pick = torch.randperm(len(x), device=x.device)[: self.mmd_points]
        return x[pick], y[pick]


def density_error(predicted: torch.Tensor, target: torch.Tensor, edge_index: torch.Tensor, radius: float,
                  mask: torch.Tensor) -> torch.Tensor:
    """Mean squared error of the predicted particles' :func:`~rgns.data.graph.kernel_density` against the target's,
    relative to the target's mean density, over the particles in ``mask``. ``edge_index`` must
    hold every pair within ``radius`` in either configuration (e.g. the union of their radius
    graphs): a pair missing from it would count in neither.

    Shapes: predicted, target ``[N, D]``, edge_index ``[2, E]``, mask ``[N]`` (bool)  ->  scalar"""
    rho, reference = kernel_density(predicted, edge_index, radius), kernel_density(target, edge_index, radius)
    scale = reference[mask].mean().detach()
    return ((rho[mask] - reference[mask]) / scale).pow(2).mean()
