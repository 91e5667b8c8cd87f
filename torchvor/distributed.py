"""Voronoi cells and k nearest neighbours of one cloud spread over the ranks of a
``torch.distributed`` process group.

Each rank passes its own points (any partition of the cloud, not necessarily
spatial) and gets the results for its own points, in its own order; indices
are global: rank r's point i is ``offset_r + i``, offsets in rank order (the
cloud is the ranks' points concatenated). The results are those of the
single-process call on that whole cloud: in float64 bit for bit for the cells
that both compute in the same pass (every cell whose neighbours the first
pass's k covers), otherwise to rounding: a retried cell's tier and precision
depend on the other cells its pass retries, and they round in another order
(as the same cell does between two single-process calls with different k).

How: the cloud is cut into slabs along the longest axis of its box, one a
rank, balanced by count; every point goes to its slab's rank, with a halo of
the points of the other slabs within a width of its slab. A rank computes its
slab's points among those (the plain op, its points ordered by global index,
so ties break as on the whole cloud) and keeps the results that the halo
certifies: a cell whose twice radius stays inside the halo (no absent point
can cut it: the radius of security), a neighbour row whose k-th distance
does. The rest run again with the halo their reach asks for, up to the whole
cloud. The results then go back to the ranks that own the points.

Periodic boxes (voronoi, lloyd): torchvor.periodic's cells with every decision
reduced over the ranks (_RankAgreement): each rank pads its own points with
their images, and the plain cells run as above over every rank's padded
points, the images' cells not computed.

Collectives are ``all_to_all_single`` and ``all_reduce`` of the points'
device: gloo for CPU tensors, NCCL for CUDA ones. Every rank of the group must
call, with points of one dtype and device kind.
"""
from __future__ import annotations

import sys
import time
import warnings
from typing import List, Optional

import torch
import torch.distributed as dist

from .graph import VoronoiGraph, voronoi_graph as _plain_graph
from . import periodic as _periodic
from .ops import DEFAULT_MEMORY_BUDGET, KNN, CellStatus, VoronoiCells, _check_on_failure
from .ops import _voronoi_rows, knn as _plain_knn
from ._slabs import (
    Group, Local, Slabs, agree, cell_columns, cell_shortfall, certify_rows, check_inside, global_batch, global_box,
    halo_rounds, send_to_owners, together)

__all__ = ["knn", "lloyd", "voronoi", "voronoi_graph"]


def _setup(points, box, batch, group, caller: str):
    """The group, points (detached), batch, boxes (B, 2, 3) in the points'
    dtype, and the slabs, after the checks every rank agrees on."""
    g = agree(points, batch, caller, group)
    points = points.detach()
    batch = global_batch(g, batch, points.shape[0])
    full_box = global_box(g, points, box, batch)
    box_arg = full_box.to(points.dtype)
    together(g, check_inside, points, batch, box_arg)
    return g, points, batch, box_arg, Slabs(g, points, full_box)


def _no_weights(caller: str, kwargs) -> None:
    """Power diagrams are computed in one process only, so far."""
    if kwargs.get("weights") is not None:
        raise NotImplementedError(f"torchvor.distributed.{caller}: weights (power diagrams) are not distributed "
                                  f"yet; call torchvor.{caller} in one process")
    kwargs.pop("weights", None)


def _start(caller: str, points, box, batch, group, kwargs):
    """A cell call's first steps: (on_failure, group, points, batch, boxes,
    this rank's slab), `kwargs` left with what the plain op takes."""
    _no_weights(caller, kwargs)
    if _periodic.periodic_axes(kwargs.pop("periodic", False), f"distributed.{caller}") is not None:
        raise NotImplementedError(f"torchvor.distributed.{caller}: periodic boxes are supported by "
                                  f"torchvor.distributed.voronoi and lloyd only, so far")
    on_failure = kwargs.pop("on_failure", "warn")
    _check_on_failure(f"distributed.{caller}", on_failure)
    g, points, batch, box_arg, slabs = _setup(points, box, batch, group, caller)
    return on_failure, g, points, batch, box_arg, Local(g, slabs, points, batch)


def _slab_cells(g: Group, local: "Local", box_arg, batched: bool, kwargs) -> VoronoiCells:
    """The cells of this rank's wanted slab points (the plain voronoi's,
    on_failure "flag"), in the order of `local.points`. The halo's cells are
    not computed: its points only bound the slab's."""
    return VoronoiCells(*_slab_rows(g, local, box_arg, batched, kwargs))


def _slab_rows(g: Group, local: "Local", box_arg, batched: bool, kwargs) -> List[torch.Tensor]:
    """_slab_cells' outputs as cell_columns gives them."""

    def compute(p, b, rows):
        return _voronoi_rows(p, box_arg, rows, b if batched else None, **kwargs)

    def shortfall(cells, clearance, rows, width):  # cells and clearance: the rows' own
        return cell_shortfall(cells, clearance)

    def extract(cells, index, rows):
        return cell_columns(cells)

    return certify_rows(g, local, compute, shortfall, extract)


def voronoi(points: torch.Tensor, box=None, *, group=None, batch: Optional[torch.Tensor] = None,
            **kwargs) -> VoronoiCells:
    """:func:`torchvor.voronoi` of the cloud that the ranks' points make
    together (rank order), each rank getting its own points' cells.

    Args:
        points: (N_r, 3) float32 or float64, this rank's points (any N_r, 0 too).
        box: as :func:`torchvor.voronoi`; None: the whole cloud's bounding box.
        group: the process group (default: the world).
        batch: (N_r,) int64 batch vector of this rank's points; the ranks'
            vectors concatenated in rank order must be sorted.
        **kwargs: ``k``, ``on_failure``, ``memory_budget`` and ``periodic``
            as :func:`torchvor.voronoi` (periodic: the box is required).

    Returns:
        :class:`torchvor.VoronoiCells` of this rank's points, in their order:
        the single-process call's results on the whole cloud. The outputs carry
        no gradient (no distributed backward yet).
    """
    _no_weights("voronoi", kwargs)
    axes = _periodic.periodic_axes(kwargs.pop("periodic", False), "distributed.voronoi")
    if axes is not None:
        return _periodic_voronoi(points, box, batch, group, axes, kwargs)
    on_failure, g, points, batch, box_arg, local = _start("voronoi", points, box, batch, group, kwargs)
    columns = _slab_rows(g, local, box_arg, batch is not None, kwargs)
    out = VoronoiCells(*local.send_home(*columns))
    _report_failures(out, on_failure, "voronoi")
    return out


class _RankAgreement(_periodic.Agreement):
    """periodic.cells over the ranks of `g`: each rank pads its own points,
    every decision is reduced over the ranks, and the plain cells are computed
    over every rank's padded points (the images' cells not computed)."""

    alone = False  # a cell that reaches past the margin asks for a wider one, the whole cloud again

    def __init__(self, g: Group):
        self.g = g

    def counts(self, pbox, batch, n):
        return self.g.reduce(_periodic.cloud_counts(pbox, batch, n), dist.ReduceOp.SUM)

    def all(self, flag: bool) -> bool:
        return bool(self.g.reduce(torch.tensor([int(flag)], device=self.g.device), dist.ReduceOp.MIN)[0])

    def any(self, flags: torch.Tensor) -> bool:
        return bool(self.g.reduce(torch.tensor([int(bool(flags.any()))], device=self.g.device),
                                  dist.ReduceOp.MAX)[0])

    def max(self, values: torch.Tensor) -> torch.Tensor:
        return self.g.reduce(values, dist.ReduceOp.MAX)

    def rows(self, points, box, rows, batch, k, memory_budget, weights=None) -> VoronoiCells:
        assert weights is None, "power cells are not distributed (voronoi raises before)"
        g = self.g.recounted(points.shape[0])
        points = points.detach()
        wanted = torch.zeros(points.shape[0], dtype=torch.bool, device=g.device)
        wanted[rows] = True
        local = Local(g, Slabs(g, points, box.double()), points, batch, wanted)
        columns = _slab_rows(g, local, box, batch is not None, {"k": k, "memory_budget": memory_budget})
        every = VoronoiCells(*local.send_back(local.wanted_index, *columns))
        return VoronoiCells(*(t[rows] for t in every))


def _periodic_setup(points, box, batch, group, axes, caller: str):
    """(group, points (detached), batch, periodic box) of a periodic call
    along `axes` (periodic_axes'), after the checks every rank agrees on."""
    g = agree(points, batch, caller, group)
    points = points.detach()
    batch = global_batch(g, batch, points.shape[0])
    if box is None:
        raise ValueError(f"torchvor.distributed.{caller}: periodic needs a box (its edges are the periods)")
    full_box = global_box(g, points, box, batch).to(points.dtype)
    pbox = together(g, _periodic.periodic_box, points, full_box, batch, axes, f"distributed.{caller}")
    together(g, check_inside, points, batch, full_box, pbox.mask)
    return g, points, batch, pbox


class _Owned:
    """A rank's own points in a periodic call (as Local for lloyd, but they
    stay on their rank: each periodic call pads and cuts them anew)."""

    def __init__(self, g: Group, points: torch.Tensor, batch: Optional[torch.Tensor], pbox):
        self.g, self.points, self.pbox, self.given_batch = g, points, pbox, batch
        self.batch = batch if batch is not None else torch.zeros(points.shape[0], dtype=torch.int64, device=g.device)
        self.index = torch.arange(g.offset, g.offset + points.shape[0], dtype=torch.int64, device=g.device)

    def cells(self, k: Optional[int], memory_budget: int = DEFAULT_MEMORY_BUDGET) -> VoronoiCells:
        found = _periodic.cells(self.points, self.pbox, self.given_batch, k, memory_budget, graph=False,
                                agreement=_RankAgreement(self.g))
        return _periodic._caller_cells(found, self.points.dtype)

    def wrap(self, points: torch.Tensor) -> torch.Tensor:
        return _periodic.wrap(points, self.pbox, self.given_batch)

    def move(self, points: torch.Tensor) -> None:
        self.points = points

    def send_back(self, index: torch.Tensor, *values: torch.Tensor) -> List[torch.Tensor]:
        return list(values)  # the rows are this rank's own, in its order


def _periodic_voronoi(points, box, batch, group, axes, kwargs) -> VoronoiCells:
    """voronoi with periodic: torchvor.periodic's cells (images, certificate,
    wider margins) with _RankAgreement."""
    on_failure = kwargs.pop("on_failure", "warn")
    _check_on_failure("distributed.voronoi", on_failure)
    unknown = set(kwargs) - {"k", "memory_budget"}
    if unknown:
        raise TypeError(f"torchvor.distributed.voronoi: unexpected keyword(s) {sorted(unknown)}")
    g, points, batch, pbox = _periodic_setup(points, box, batch, group, axes, "voronoi")
    out = _Owned(g, points, batch, pbox).cells(kwargs.get("k"), kwargs.get("memory_budget", DEFAULT_MEMORY_BUDGET))
    _report_failures(out, on_failure, "voronoi")
    return out


def voronoi_graph(points: torch.Tensor, box=None, *, group=None, batch: Optional[torch.Tensor] = None,
                  **kwargs) -> VoronoiGraph:
    """:func:`torchvor.voronoi_graph` of the cloud that the ranks' points make
    together (rank order), each rank getting its own cells and their faces.

    Args:
        points, box, group, batch: as :func:`voronoi`.
        **kwargs: ``k``, ``on_failure``, ``memory_budget`` as :func:`torchvor.voronoi_graph`.

    Returns:
        :class:`torchvor.VoronoiGraph` of this rank's cells: ``edge_index``
        (2, E_r) holds global indices (row 1 this rank's points, sorted by it
        then row 0), ``wall_area`` and ``cells`` this rank's rows in its
        order: the single-process call's on the whole cloud (each face is the
        mean of what its two cells computed, so a cell counts as computed when
        its neighbours are too). No gradient.
    """
    on_failure, g, points, batch, box_arg, local = _start("voronoi_graph", points, box, batch, group, kwargs)

    def compute(p, b):
        return _plain_graph(p, box_arg, batch=b if batch is not None else None, on_failure="flag", **kwargs)

    def shortfall(graph, clearance, rows, width):
        own_cell = cell_shortfall(graph.cells, clearance)
        source, target = graph.edge_index
        worst = own_cell.scatter_reduce(0, target, own_cell[source], "amax")  # and every neighbour's
        return worst[rows]

    index, rows, graph = halo_rounds(g, local, compute, shortfall)
    own = torch.zeros(index.numel(), dtype=torch.bool, device=g.device)
    own[rows] = True
    source, target = graph.edge_index
    mine = own[target]
    edges = torch.stack([index[source[mine]], index[target[mine]]], 1)
    faces = torch.cat([graph.area[mine].unsqueeze(1), graph.centroid[mine]], 1)
    edges, faces = local.send_edges(edges, faces)
    key = edges[:, 1] * max(g.total, 1) + edges[:, 0]  # by cell, then neighbour
    order = torch.sort(key).indices
    edges, faces = edges[order], faces[order]
    *columns, wall_area = local.send_home(*cell_columns(graph.cells, rows), graph.wall_area[rows])
    cells = VoronoiCells(*columns)
    _report_failures(cells, on_failure, "voronoi_graph")
    return VoronoiGraph(edges.t().contiguous(), faces[:, 0].contiguous(), faces[:, 1:4].contiguous(), wall_area, cells)


def lloyd(points: torch.Tensor, box=None, iters: int = 10, *, group=None, tol: Optional[float] = None,
          k: Optional[int] = None, batch: Optional[torch.Tensor] = None, progress: bool = False, callback=None,
          return_history: bool = False, periodic=False):
    """:func:`torchvor.lloyd` of the cloud that the ranks' points make together
    (rank order), each rank getting its own points relaxed, in its order.

    Each iteration computes the cells over the ranks (:func:`voronoi`; the
    slabs are cut once) and moves every point to its cell's centroid (a point
    whose cell failed stays, with a RuntimeWarning on its rank), as the
    single-process relaxation does: the same points, bit for bit in float64.

    Args:
        points, box, group, batch: as :func:`voronoi` (box None: the first
            points' bounding box, kept for every iteration).
        iters, tol, k, progress, return_history: as :func:`torchvor.lloyd`;
            ``tol`` and the history's measures are over the whole cloud
            (``neighbors_needed``: the largest of the ranks' percentiles;
            ``k``: the given k, or 0 where each call's pilot picks it);
            ``progress`` prints on rank 0.
        callback: ``callback(iteration, points, cells)`` on every rank with its
            own moved points and cells; True on any rank stops every rank.
        periodic: as :func:`torchvor.lloyd` (the box required): each
            iteration is a periodic :func:`voronoi`, the points wrapped into the
            box, and they stay on their owners' ranks.

    Returns:
        This rank's relaxed points (a new tensor), or ``(points, history)``.
    """
    from .lloyd import LloydStep, _progress_line, neighbors_quantile

    if not isinstance(iters, int) or isinstance(iters, bool) or iters < 0:
        raise ValueError(f"torchvor.distributed.lloyd: iters must be a non-negative int, got {iters!r}")
    if tol is not None and not tol >= 0:
        raise ValueError(f"torchvor.distributed.lloyd: tol must be None or >= 0, got {tol!r}")
    if k is not None and (not isinstance(k, int) or isinstance(k, bool) or k < 1):
        raise ValueError(f"torchvor.distributed.lloyd: k must be None or a positive int, got {k!r}")
    axes = _periodic.periodic_axes(periodic, "distributed.lloyd")
    if axes is not None:
        g, current, batch, pbox = _periodic_setup(points, box, batch, group, axes, "lloyd")
        box_arg = pbox.box
        local = _Owned(g, current, batch, pbox)
    else:
        g, current, batch, box_arg, slabs = _setup(points, box, batch, group, "lloyd")
        # the points stay on their slabs' ranks between iterations; those that cross a boundary move
        local = Local(g, slabs, current, batch)
    edges = (box_arg[:, 1] - box_arg[:, 0]).double().norm(dim=1)
    history = []
    for iteration in range(iters):
        start = time.perf_counter()
        if axes is not None:
            cells = local.cells(k)
        else:
            cells = _slab_cells(g, local, box_arg, batch is not None, {"k": k})
        computed = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
        target = torch.where(computed.unsqueeze(1), cells.centroid, local.points)
        needed = neighbors_quantile(cells.neighbors_needed[computed])
        diagonal = edges[local.batch] if batch is not None else edges[0].expand(target.shape[0])
        moves = ((target - local.points).double().norm(dim=1) / diagonal).max() if target.shape[0] else \
            torch.zeros((), dtype=torch.float64, device=g.device)
        moved = local.wrap(target)
        sums = g.reduce(torch.stack([cells.second_moment.double().sum(), (~computed).sum().double()]),
                        dist.ReduceOp.SUM)
        maxima = g.reduce(torch.stack([moves.double(), torch.tensor(float(needed), dtype=torch.float64,
                                                                    device=g.device)]), dist.ReduceOp.MAX)
        energy, failed = float(sums[0]), int(sums[1])
        mine_failed = int((~computed).sum())
        if mine_failed:
            warnings.warn(f"torchvor.distributed.lloyd: {mine_failed} cell(s) could not be computed in iteration "
                          f"{iteration}; their points stay in place", RuntimeWarning, stacklevel=2)
        step = LloydStep(iteration=iteration, energy=energy, max_displacement=float(maxima[0]),
                         seconds=time.perf_counter() - start, k=k or 0, neighbors_needed=int(maxima[1]),
                         failed=failed)
        history.append(step)
        stop = False
        if callback is not None:  # the caller's rows and order
            mine, *columns = local.send_back(local.index, moved, *cell_columns(cells))
            stop = callback(iteration, mine, VoronoiCells(*columns)) is True
        local.move(moved)
        if progress and g.rank == 0:
            print(_progress_line(step, iters), file=sys.stderr, flush=True)
        stop = bool(g.reduce(torch.tensor([int(stop)], device=g.device), dist.ReduceOp.MAX)[0])
        if stop or (tol is not None and step.max_displacement < tol):
            break
    (current,) = local.send_back(local.index, local.points)
    return (current, history) if return_history else current


def _report_failures(cells: VoronoiCells, on_failure: str, caller: str) -> None:
    """on_failure of voronoi and voronoi_graph for this rank's cells."""
    ok = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
    failed = int((~ok).sum())
    if failed and on_failure != "flag":
        message = f"torchvor.distributed.{caller}: {failed} cell(s) could not be computed (NaN outputs)"
        if on_failure == "raise":
            raise RuntimeError(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def knn(points: torch.Tensor, k: int, queries: Optional[torch.Tensor] = None, *, group=None,
        batch: Optional[torch.Tensor] = None, query_batch: Optional[torch.Tensor] = None,
        exclude_self: Optional[bool] = None) -> KNN:
    """:func:`torchvor.knn` in the cloud that the ranks' points make together
    (rank order), for this rank's queries.

    Args:
        points: (N_r, 3) float32 or float64, this rank's points.
        k: neighbours a row, ``k >= 1``.
        queries: (M_r, 3) this rank's queries (the points' dtype); None: its points.
        group: the process group (default: the world).
        batch, query_batch: (N_r,) and (M_r,) int64 batch vectors; the ranks'
            vectors concatenated in rank order must be sorted; a query sees only
            points of its batch element (query_batch is required with batch
            where queries are given, as in :func:`torchvor.knn`).
        exclude_self: with queries None, whether a point skips itself (default True).

    Returns:
        :class:`torchvor.KNN` (dist2, idx), (M_r, k): idx are global indices
        into the whole cloud (rank r's point i is ``offset_r + i``), as the
        single-process call gives them; missing neighbours are inf / -1.
    """
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise ValueError(f"torchvor.distributed.knn: k must be an int >= 1, got {k!r}")
    if queries is not None and exclude_self:
        raise ValueError("torchvor.distributed.knn: exclude_self applies only when queries is None")
    g = agree(points, batch, "knn", group)
    points = points.detach()
    batch = global_batch(g, batch, points.shape[0])
    slabs = Slabs(g, points, global_box(g, points, None, batch))
    local = Local(g, slabs, points, batch)
    skip = queries is None and (exclude_self is None or bool(exclude_self))
    asked = None if queries is None else _Queries(g, slabs, points, batch, queries.detach(), query_batch)

    def compute(p, b, rows=None):  # every row's neighbours (they are cheap beside the exchanges)
        if asked is None:
            return _plain_knn(p, k, batch=b if batch is not None else None, exclude_self=skip)
        return _plain_knn(p, k, asked.points, batch=b if batch is not None else None,
                          query_batch=asked.batch if batch is not None else None)

    def shortfall(result, clearance, rows, width):
        if asked is None:  # certify_rows': the rows' clearance
            rows_clearance = clearance
        else:
            rows_clearance = slabs.clearance(asked.points[:, slabs.axis], g.rank, width)
            rows = slice(None)
        last = torch.sqrt(result.dist2[rows, -1].double())  # inf where a row is short of k: the whole cloud decides
        return (last - rows_clearance).clamp_min(0)

    def extract(result, index, rows):
        idx = result.idx[rows]
        return [result.dist2[rows], torch.where(idx >= 0, index[idx.clamp_min(0)], idx)]  # global indices

    if asked is None:
        return KNN(*local.send_home(*certify_rows(g, local, compute, shortfall, extract)))
    index, _, result = halo_rounds(g, local, compute, shortfall)
    return KNN(*asked.send_back(*extract(result, index, slice(None))))


class _Queries:
    """This rank's slab's queries (sorted by global query index), routed by
    coordinate as the points are, and how their rows go back."""

    def __init__(self, g: Group, slabs: Slabs, points, batch, queries: torch.Tensor, query_batch):
        problem = None
        if not isinstance(queries, torch.Tensor) or queries.dim() != 2 or queries.shape[1] != 3:
            problem = "queries must have shape (M, 3)"
        elif queries.dtype != points.dtype or not bool(torch.isfinite(queries).all()):
            problem = "queries must have the points' dtype and be finite"
        elif batch is not None and (query_batch is None or query_batch.shape != (queries.shape[0],)):
            problem = "query_batch (M,) is required with batch when queries are given"
        together(g, _raise_if, problem)
        self.g = g
        m = queries.shape[0]
        self.counts = g.all_gather_int(m)
        self.offset = sum(self.counts[: g.rank])
        if batch is not None:
            global_batch(g, query_batch, m, self.counts)
        qindex = torch.arange(self.offset, self.offset + m, dtype=torch.int64, device=g.device)
        qbatch = query_batch if batch is not None else torch.zeros(m, dtype=torch.int64, device=g.device)
        got = g.exchange(slabs.owner(queries[:, slabs.axis]), [queries, qindex, qbatch])
        order = torch.sort(got[1]).indices
        self.points, self.index, self.batch = (t[order] for t in got)

    def send_back(self, *values: torch.Tensor) -> List[torch.Tensor]:
        """Each of `values`, rows of the slab's queries, sent to the ranks that asked them."""
        return send_to_owners(self.g, self.counts, self.index, values)


def _raise_if(problem: Optional[str]) -> None:
    if problem is not None:
        raise ValueError(f"torchvor.distributed.knn: {problem}")
