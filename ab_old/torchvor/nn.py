"""torch.nn wrappers of torchvor's point-set operations."""
from __future__ import annotations

from typing import Optional

import torch

from .lloyd import lloyd
from .ops import BoxLike


class LloydRelaxation(torch.nn.Module):
    """Lloyd relaxation of a point set as a module (see :func:`torchvor.lloyd.lloyd`).

    No gradient flows through it: the output is a new tensor detached from
    the input's graph (Lloyd's fixed-point iteration is a preprocessing step,
    not a differentiable layer; use :func:`torchvor.cvt.cvt_energy` to
    optimise positions with gradients). The module has no parameters or buffers.

    Args:
        iters: maximum number of Lloyd iterations.
        box: the fixed box, as accepted by :func:`torchvor.voronoi`; None uses
            the bounding box of each input (per batch element).
        tol: early-stopping threshold on the largest displacement relative to
            the box diagonal (None: always run ``iters`` iterations).

    Shape:
        forward(points (N, 3) float32/float64 on any device, batch (N,) int64
        optional) -> (N, 3) with the same dtype and device.
    """

    def __init__(self, iters: int = 10, box: Optional[BoxLike] = None, tol: Optional[float] = None):
        super().__init__()
        if not isinstance(iters, int) or iters < 0:
            raise ValueError(f"LloydRelaxation: iters must be a non-negative int, got {iters!r}")
        self.iters = iters
        self.box = box
        self.tol = tol

    def forward(self, points: torch.Tensor, batch: Optional[torch.Tensor] = None) -> torch.Tensor:
        with torch.no_grad():
            return lloyd(points, self.box, self.iters, tol=self.tol, batch=batch)

    def extra_repr(self) -> str:
        box = "bounding box" if self.box is None else "fixed"
        return f"iters={self.iters}, box={box}, tol={self.tol}"


__all__ = ["LloydRelaxation"]
