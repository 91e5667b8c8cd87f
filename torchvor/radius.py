"""Radius neighbourhoods: every point within distance r of each query, and the radius graph.

Thin layer over ``torch.ops.torchvor.radius`` (csrc/ops/radius.h): its fake
kernel (the edge count depends on the data) and its autograd formula.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from .ops import BoxLike, PeriodicLike, _check_points, _queries_of, knn  # loads torchvor._C
from . import periodic as _periodic


class Radius(NamedTuple):
    """Result of :func:`radius`.

    edge_index: (2, E) int64, PyG's layout: ``edge_index[0]`` the point (source),
        ``edge_index[1]`` the query (target); sorted by query, then distance,
        then point index.
    dist2: (E,) squared distances, points' dtype; differentiable with respect
        to the points and the queries.
    """

    edge_index: torch.Tensor
    dist2: torch.Tensor


def radius(
    points: torch.Tensor,
    r: float,
    queries: Optional[torch.Tensor] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    query_batch: Optional[torch.Tensor] = None,
    max_num_neighbors: Optional[int] = None,
    exclude_self: Optional[bool] = None,
    box: Optional[BoxLike] = None,
    periodic: PeriodicLike = False,
) -> Radius:
    """Every point within distance ``r`` of each query (``|p - q| <= r``), on a uniform grid.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA.
        r: the radius, a finite number ``>= 0``.
        queries: (M, 3), same dtype and device; ``None`` queries the points themselves.
        batch: (N,) int64 sorted batch vector (PyG convention) for ragged clouds.
        query_batch: (M,) int64 sorted batch vector of the queries; defaults to
            ``batch`` when ``queries`` is None, and is required with ``batch``
            otherwise. Queries only see points of their own batch element.
        max_num_neighbors: keep at most this many points a query, its nearest
            (ties by the lower index); ``None`` (default) keeps every one. With
            a cap, memory is (M, max_num_neighbors) during the search; without,
            the output's own.
        exclude_self: when ``queries`` is None, whether query i skips point i.
            Default True (exact duplicates of a point are still its
            neighbours, at distance 0). Must be False/None when queries are given.
        box, periodic: as :func:`torchvor.knn`: distances wrap around the box
            along the periodic axes, each point at most once a query, at its
            nearest image.

    Returns:
        :class:`Radius` ``(edge_index, dist2)``, E edges sorted by query, then distance.
    """
    own = queries is None
    queries, query_batch, exclude_self = _queries_of("radius", points, queries, batch, query_batch, exclude_self)
    if isinstance(r, torch.Tensor) and r.numel() == 1:
        r = r.item()
    if isinstance(r, bool) or not isinstance(r, (int, float)):
        raise TypeError(f"torchvor.radius: r must be a number, got {type(r).__name__}")
    r = float(r)
    if not (math.isfinite(r) and r >= 0):
        raise ValueError(f"torchvor.radius: r must be finite and non-negative, got {r}")
    if max_num_neighbors is not None:
        if isinstance(max_num_neighbors, bool) or not isinstance(max_num_neighbors, int):
            raise TypeError(f"torchvor.radius: max_num_neighbors must be an int or None, "
                            f"got {type(max_num_neighbors).__name__}")
        if max_num_neighbors < 1:
            raise ValueError(f"torchvor.radius: max_num_neighbors must be at least 1, got {max_num_neighbors}")
    axes = _periodic.periodic_axes(periodic, "radius")
    if axes is not None:
        _check_points(points, "radius")
        pbox = _periodic.periodic_box(points, box, batch, axes, "radius")
        idx, row, dist2 = _periodic.radius(points, r, None if own else queries, batch, query_batch,
                                           max_num_neighbors, exclude_self, pbox)
        return Radius(torch.stack([idx, row]), dist2)
    if max_num_neighbors is not None:
        return _nearest_within(points, r, queries, batch, query_batch, max_num_neighbors, exclude_self)
    idx, row, dist2 = torch.ops.torchvor.radius.default(points, queries, r, batch, query_batch, exclude_self)
    return Radius(torch.stack([idx, row]), dist2)


def _nearest_within(points, r, queries, batch, query_batch, cap, exclude_self) -> Radius:
    """The nearest `cap` points of each query, those within r: a kNN of k = cap
    (memory M x cap), sorted as the kNN sorts, by distance then index."""
    if exclude_self:  # the queries are the points
        result = knn(points, cap, batch=batch, exclude_self=True)
    else:
        result = knn(points, cap, queries, batch=batch, query_batch=query_batch)
    row = torch.arange(queries.shape[0], device=queries.device).repeat_interleave(cap)
    rounded = torch.tensor(r, dtype=torch.float64).to(result.dist2.dtype)  # r^2 rounded as the op rounds it
    edge_index = torch.stack([result.idx.reshape(-1), row])
    within = (result.idx.reshape(-1) >= 0) & (result.dist2.reshape(-1) <= rounded * rounded)
    return Radius(edge_index[:, within], result.dist2.reshape(-1)[within])


def radius_graph(
    points: torch.Tensor,
    r: float,
    batch: Optional[torch.Tensor] = None,
    loop: bool = False,
    max_num_neighbors: Optional[int] = None,
    *,
    box: Optional[BoxLike] = None,
    periodic: PeriodicLike = False,
) -> torch.Tensor:
    """The radius graph in PyG's layout: an edge j -> i for every pair within distance ``r``.

    Args:
        points: (N, 3) float32/float64, CPU or CUDA.
        r: the radius (``|x_j - x_i| <= r``).
        batch: optional (N,) int64 sorted batch vector; clouds never connect.
        loop: include the self-loops i -> i.
        max_num_neighbors: keep at most this many neighbours a point, its
            nearest; ``None`` (default) keeps every one.
        box, periodic: as :func:`torchvor.knn` (a periodic edge joins i to the
            nearest image of j).

    Returns:
        edge_index: (2, E) int64, ``edge_index[0]`` the neighbour j (source),
        ``edge_index[1]`` the centre i (target), sorted by centre, then
        distance, then neighbour. Without a cap every pair appears in both directions.
    """
    return radius(points, r, batch=batch, max_num_neighbors=max_num_neighbors, exclude_self=not loop,
                  box=box, periodic=periodic).edge_index


@torch.library.register_fake("torchvor::radius")
def _radius_fake(points, queries, r, batch=None, query_batch=None, exclude_self=False):
    edges = torch.library.get_ctx().new_dynamic_size()  # depends on the data
    return (queries.new_empty((edges,), dtype=torch.int64), queries.new_empty((edges,), dtype=torch.int64),
            queries.new_empty((edges,)))


# dist2 = |q - p|^2: d dist2 = 2 (q - p) . (dq - dp); the indices are piecewise constant.
def _radius_setup_context(ctx, inputs, output) -> None:
    points, queries = inputs[0], inputs[1]
    idx, row, _dist2 = output
    ctx.mark_non_differentiable(idx, row)
    ctx.save_for_backward(points, queries, idx, row)


def _radius_backward(ctx, _grad_idx, _grad_row, grad_dist2):
    points, queries, idx, row = ctx.saved_tensors
    toward_query = 2 * grad_dist2.unsqueeze(-1) * (queries[row] - points[idx])  # (E, 3)
    grad_points = grad_queries = None
    if ctx.needs_input_grad[1]:
        grad_queries = torch.zeros_like(queries).index_add(0, row, toward_query)
    if ctx.needs_input_grad[0]:
        grad_points = torch.zeros_like(points).index_add(0, idx, -toward_query)
    return grad_points, grad_queries, None, None, None, None


torch.library.register_autograd("torchvor::radius", _radius_backward, setup_context=_radius_setup_context)
