"""CVT (centroidal Voronoi tessellation) energy, differentiable in the points.

The energy of points x_i with Voronoi cells V_i (clipped to a box) is

    E(x) = sum_i  integral over V_i of |y - x_i|^2 dy,

the sum of the cells' second moments about their seeds. Its gradient has the
closed form (Du, Faber & Gunzburger 1999)

    dE/dx_i = 2 m_i (x_i - c_i),

m_i the volume and c_i the centroid of V_i: the terms from moving cell
boundaries cancel because neighbouring integrands agree on every bisector.
Lloyd's algorithm (:mod:`torchvor.lloyd`) is the fixed-point iteration
x_i <- c_i of this gradient; :func:`cvt_energy` lets any torch optimiser use it.

The op ``torchvor::cvt_energy`` is declared in C++ (csrc/registration.cpp,
with every other schema); its kernel, fake kernel and autograd formula are
registered here in Python, over ``torchvor::voronoi_cells``, so it works under
``torch.compile(fullgraph=True)`` and passes ``torch.library.opcheck``.
"""
from __future__ import annotations

from typing import Optional, Tuple

import torch
from torch.autograd.function import once_differentiable

from . import ops as _ops  # loads torchvor._C (the schemas) and voronoi_cells' fake kernel
from .ops import BoxLike

# torchvor::cvt_energy(Tensor points, Tensor box, Tensor? batch, int? k)
#     -> (Tensor energy, Tensor gradient)
# The kernel is a composite of torchvor::voronoi_cells, which dispatches by
# device itself; its autograd is the formula below, not a trace of the kernel.


@torch.library.impl("torchvor::cvt_energy", "CompositeExplicitAutograd")
def _cvt_energy_kernel(
    points: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor], k: Optional[int]
) -> Tuple[torch.Tensor, torch.Tensor]:
    """(energy, gradient): energy () = sum of second moments; gradient (N, 3) = dE/dpoints.

    The gradient is an output rather than something recomputed in backward
    because setup_context only sees inputs and outputs, and it costs three
    flops per point next to the Voronoi cells themselves.
    """
    volume, centroid, second_moment, _status, _neighbors_needed, _radius = torch.ops.torchvor.voronoi_cells.default(
        points, box, batch, k
    )
    energy = second_moment.sum()
    gradient = 2.0 * volume.unsqueeze(1) * (points - centroid)
    return energy, gradient


@torch.library.register_fake("torchvor::cvt_energy")
def _cvt_energy_fake(points, box, batch, k):
    return points.new_empty(()), points.new_empty(points.shape)


def _cvt_energy_setup_context(ctx, inputs, output) -> None:
    _energy, gradient = output
    # The gradient output is a by-product, not a function to differentiate.
    ctx.mark_non_differentiable(gradient)
    ctx.save_for_backward(gradient)


@torch.autograd.function.once_differentiable
def _cvt_energy_backward(ctx, grad_energy, _grad_gradient):
    # once_differentiable: the saved gradient is a constant here, so a double
    # backward would silently give a zero Hessian; it raises instead.
    (gradient,) = ctx.saved_tensors
    # Box, batch and k get no gradient: the box is treated as a constant.
    return grad_energy * gradient, None, None, None


torch.library.register_autograd("torchvor::cvt_energy", _cvt_energy_backward,
                                setup_context=_cvt_energy_setup_context)

_cvt_energy_op = torch.ops.torchvor.cvt_energy.default


class _EnergyWithGradient(torch.autograd.Function):
    """An energy computed apart, with its gradient (first order only): the
    periodic energy, whose cells come from torchvor.periodic."""

    @staticmethod
    def forward(ctx, points, energy, gradient):
        ctx.save_for_backward(gradient)
        return energy.clone()

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_energy):
        (gradient,) = ctx.saved_tensors
        return grad_energy * gradient, None, None


def cvt_energy(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    k: Optional[int] = None,
    periodic: _ops.PeriodicLike = False,
    weights: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """CVT energy: the sum over Voronoi cells of ``integral |y - x_i|^2 dy``.

    Differentiable in ``points``, first order only (a double backward raises),
    with dE/dx_i = 2 m_i (x_i - c_i).
    The box is treated as a constant: no gradient flows into it, even when it
    is derived from the points (``box=None``). With ``batch`` the energies of
    all clouds are summed.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside the box.
        box: None (bounding box of the points, per batch element), ``(lo, hi)``,
            a (2, 3) tensor, or (B, 2, 3) with ``batch``.
        batch: optional (N,) int64 sorted batch vector.
        k: first-pass neighbour count of the cell computation (default: measured
            on a pilot sample); any k gives exact cells, one close to what cells
            need is fastest.
        periodic: as :func:`torchvor.voronoi` (the box is then required).
        weights: (N,) as :func:`torchvor.voronoi`: the sum over the power
            cells (an empty cell adds 0), differentiable in the weights
            (``dE/dw_j`` from the faces' motion), not in the points (that
            backward raises).

    Returns:
        A 0-dim tensor of the points' dtype and device. It is NaN when a cell
        could not be computed (see ``torchvor.voronoi``).

    Raises:
        ValueError: bad shapes, NaN/Inf, points outside the box, k < 1.
        TypeError: non-floating points or mismatched dtypes.
    """
    axes = _ops._periodic.periodic_axes(periodic, "cvt_energy")
    if weights is not None:
        cells = _ops.voronoi(points, box, batch=batch, k=k, periodic=periodic, weights=weights, on_failure="flag")
        return cells.second_moment.sum()
    if axes is not None:
        _ops._check_tensor(points, "points")
        _ops._check_points(points, "cvt_energy")
        pbox = _ops._periodic.periodic_box(points.detach(), box, batch, axes, "cvt_energy")
        with torch.no_grad():
            cells = _ops._periodic.voronoi(points.detach(), pbox, batch, k, _ops.DEFAULT_MEMORY_BUDGET)
            gradient = 2.0 * cells.volume.unsqueeze(1) * (points.detach() - cells.centroid)
        return _EnergyWithGradient.apply(points, cells.second_moment.sum(), gradient)
    box_tensor = _ops.as_box(points, box, batch)
    if box is None:
        # The box is constant by contract; derived from points it would
        # otherwise carry their autograd history into the op.
        box_tensor = box_tensor.detach()
    energy, _gradient = _cvt_energy_op(points, box_tensor, batch, k)
    return energy


__all__ = ["cvt_energy"]
