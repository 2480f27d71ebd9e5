"""Static obstacles shared by the solvers and the scene generators (plain numpy)."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Capsule:
    """A segment ``start``-``end`` thickened by ``radius``: a ramp in 2D, a rod in 3D.

    Its signed distance is ``|p - closest point on the segment| - radius``: negative inside.
    """

    start: tuple[float, ...]
    end: tuple[float, ...]
    radius: float

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """``points [N, D]`` -> ``[N]`` signed distance to the capsule's surface."""
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        ab = b - a
        t = np.clip((points - a) @ ab / max(ab @ ab, 1e-12), 0.0, 1.0)
        return np.linalg.norm(points - (a + t[:, None] * ab), axis=-1) - self.radius

    def sample(self, spacing: float) -> np.ndarray:
        """Static particles along the segment, ``spacing`` apart: ``[M, D]``."""
        a, b = np.asarray(self.start, float), np.asarray(self.end, float)
        count = max(int(np.ceil(np.linalg.norm(b - a) / spacing)), 1) + 1
        return a + np.linspace(0.0, 1.0, count)[:, None] * (b - a)


def lattice(lower: np.ndarray, upper: np.ndarray, spacing: float) -> np.ndarray:
    """Cell-centred points ``spacing`` apart filling the box [lower, upper]: ``[M, D]``."""
    counts = np.maximum(np.floor((upper - lower) / spacing + 1e-6).astype(int), 1)
    index = np.stack(np.meshgrid(*[np.arange(c) for c in counts], indexing="ij"), -1).reshape(-1, len(counts))
    offset = lower + 0.5 * ((upper - lower) - counts * spacing)  # centre the block in the box
    return offset + (index + 0.5) * spacing
