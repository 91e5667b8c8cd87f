"""Lloyd relaxation: move every point to the centroid of its Voronoi cell, repeatedly.

Each iteration computes all cells with :func:`torchvor.voronoi` and replaces
every point by its cell's centroid, which never increases the CVT energy
(:func:`torchvor.cvt.cvt_energy`); the points drift towards a centroidal
Voronoi tessellation (blue noise when started from white noise).

The first-pass neighbour count ``k`` of the cell computation adapts to the
point set (paper §5.2): white noise needs large neighbourhoods in the first
iterations, relaxed points small ones. The first iteration takes the k of
the op's pilot sample (as ``voronoi`` does by default), so that points that
are already relaxed do not fetch white noise's large neighbourhoods for
every cell. Each iteration measures how many neighbours every cell needed
and the next one fetches the 99th percentile of that plus a small margin,
so the few cells that need more are recomputed (automatically, by
``voronoi``) instead of all cells fetching too many.

The points are kept in the order of the cell computation's grid (cells of
nearby points in nearby rows): each iteration (one op, ``torchvor::lloyd_step``)
gets its cells and the moved points in that order with the permutation, so neither
the scattered gather back to the caller's rows nor, from the second
iteration on, the scattered gather of the points into grid order is paid;
the caller's order comes back once, at the end.
"""
from __future__ import annotations

import math
import sys
import warnings
import time
from dataclasses import dataclass
from typing import Callable, List, Optional, Tuple, Union

import numpy as np
import torch

from .ops import (DEFAULT_MEMORY_BUDGET, BoxLike, CellStatus, PeriodicLike, VoronoiCells, _box_for_call,
                  _check_points, _periodic)

MIN_K, MAX_K = 8, 256
K_QUANTILE = 0.99   # share of cells that the adapted k should cover in one pass
K_MARGIN = 2        # cells need slightly fewer neighbours as points relax; a small margin suffices
QUANTILE_SAMPLE = 1 << 16  # the quantile is taken over every cell up to this many, else a strided sample
HISTOGRAM_BINS = 1024      # neighbour counts the quantile's histogram holds (MAX_K is far below)


@dataclass
class LloydStep:
    """What one Lloyd iteration measured (entries of the history).

    iteration: 0-based index of the iteration.
    energy: CVT energy of the points *before* this iteration's move (sum of the
        second moments of the cells computed in this iteration); NaN if a cell failed.
    max_displacement: largest distance a point moved in this iteration,
        divided by the diagonal of its box.
    seconds: wall time of the iteration (synchronised, so exact on CUDA too).
    k: first-pass neighbour count used for the cells (the first iteration's,
        with ``k=None``, from the op's pilot sample; at most the largest
        cloud's point count; 0 for no points).
    neighbors_needed: the 99th percentile of the neighbours the cells needed
        (what the next iteration's k is derived from); beyond 65536 cells,
        that of an evenly strided sample of 65536 to 131071 of them.
    failed: number of cells that could not be computed (their points stayed put).
    """

    iteration: int
    energy: float
    max_displacement: float
    seconds: float
    k: int
    neighbors_needed: int
    failed: int


Callback = Callable[[int, torch.Tensor, VoronoiCells], Optional[bool]]


def lloyd(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    iters: int = 10,
    *,
    tol: Optional[float] = None,
    k: Optional[int] = None,
    batch: Optional[torch.Tensor] = None,
    progress: bool = False,
    callback: Optional[Callback] = None,
    return_history: bool = False,
    periodic: PeriodicLike = False,
    volumes: Optional[torch.Tensor] = None,
) -> Union[torch.Tensor, Tuple[torch.Tensor, List[LloydStep]]]:
    """Relax ``points`` by ``iters`` Lloyd iterations inside a fixed box.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``. Not modified.
        box: None (bounding box of the input points, per batch element,
            computed once), ``(lo, hi)``, a (2, 3) tensor, or (B, 2, 3) with
            ``batch``. The box stays fixed for all iterations.
        iters: maximum number of iterations (>= 0).
        tol: stop early once an iteration moves no point farther than
            ``tol`` times the diagonal of its box (checked after the move,
            so that iteration's move is kept). None: run all ``iters``.
        k: fixed first-pass neighbour count for every iteration. None (default):
            the first iteration measures it on a pilot sample of cells (as
            ``torchvor.voronoi`` does: ~19 for blue noise, ~66 for white
            noise), and each later one adapts it to the 99th percentile of
            the neighbours the previous iteration's cells needed (plus 2),
            clamped to [8, 256]. Any k gives the same, exact cells; it only
            changes speed.
        batch: optional (N,) int64 sorted batch vector: each cloud relaxes in
            its own box, independently.
        progress: print one line per iteration to stderr (iteration, energy,
            max displacement, k, time).
        callback: ``callback(iteration, points, cells)`` after each iteration,
            with the 0-based iteration index, the moved points and the
            :class:`~torchvor.VoronoiCells` of the points before the move.
            Returning True stops the relaxation. Do not modify ``points`` in place.
        return_history: also return the list of :class:`LloydStep`, one per
            iteration run.
        periodic: as :func:`torchvor.voronoi` (the box is then required): the
            cells wrap around and each moved point is wrapped into the box.
            Each iteration is a periodic ``voronoi`` call (the cloud padded
            with images, :mod:`torchvor.periodic`), with ``k`` adapted the
            same way; ``LloydStep.k`` is then the k given (0: each call's pilot's).
        volumes: (N,) target volumes in proportion: capacity-constrained
            Lloyd instead (:func:`torchvor.power_lloyd`: each iteration gives
            every power cell its volume, then moves the points to the power
            cells' centroids). Takes ``box``, ``iters``, ``tol``, ``k``,
            ``progress`` and ``periodic``; not ``batch``, ``callback`` or
            ``return_history`` (ValueError).

    Returns:
        The relaxed points, a new (N, 3) tensor with the input's dtype and
        device (not attached to any autograd graph), or
        ``(points, history)`` when ``return_history`` is True.

    Raises:
        ValueError: bad shapes, NaN/Inf, points outside the box, negative
            ``iters``, ``k < 1`` or a negative ``tol``.
        TypeError: non-tensor or non-floating points.

    A cell that cannot be computed (see ``torchvor.voronoi``) raises a
    RuntimeWarning; its point keeps its place in that iteration and the
    recorded energy is NaN.
    """
    _check_arguments(points, iters, tol, k)
    if volumes is not None:
        unsupported = [name for name, value in (("batch", batch), ("callback", callback)) if value is not None]
        unsupported += ["return_history"] if return_history else []
        if unsupported:
            raise ValueError(f"torchvor.lloyd: volumes (capacity-constrained Lloyd) does not take {', '.join(unsupported)}")
        from .transport import power_lloyd

        return power_lloyd(points, box, iters, volumes=volumes, k=k, progress=progress, move_tol=tol,
                           periodic=periodic)[0]
    current = points.detach()  # never written in place: each iteration makes a new tensor
    axes = _periodic.periodic_axes(periodic, "lloyd")
    if axes is not None:
        _check_points(current, "lloyd")
        pbox = _periodic.periodic_box(current, box, batch, axes, "lloyd")

        def one_step(current, batch, k):
            return _periodic_step(current, pbox, batch, k)
    else:
        box_tensor = _box_for_call(current, box, batch).detach()

        def one_step(current, batch, k):
            return _step(current, box_tensor, batch, k)
    # `current` (and the batch) in grid order: row i holds the caller's point
    # row_of[i] (None: the caller's order).
    row_of: Optional[torch.Tensor] = None
    next_k: Optional[int] = k  # None: the op's pilot picks the first iteration's
    history: List[LloydStep] = []
    for iteration in range(iters):
        start = time.perf_counter()
        # Failures are flagged, and reported below from the op's single read.
        moved, cells, order, energy, max_displacement, used_k, failed, needed = one_step(current, batch, next_k)
        row_of = order if row_of is None else row_of.index_select(0, order)
        if batch is not None:  # the grid order sorts by batch element first: still sorted
            batch = batch.index_select(0, order)
        if failed:
            warnings.warn(f"torchvor.lloyd: {failed} cell(s) could not be computed in iteration "
                          f"{iteration}; their points stay in place", RuntimeWarning, stacklevel=2)
        step = LloydStep(
            iteration=iteration,
            energy=energy,
            max_displacement=max_displacement,
            seconds=time.perf_counter() - start,  # after the read above, which synchronises CUDA
            k=used_k,
            neighbors_needed=needed,
            failed=failed,
        )
        history.append(step)
        current = moved
        if progress:
            print(_progress_line(step, iters), file=sys.stderr, flush=True)
        if k is None:
            next_k = _adapted_k(needed)
        # The callback sees the caller's order (two gathers more an iteration, only with a callback).
        stop_requested = callback is not None and callback(
            iteration, _to_caller_order(current, row_of),
            VoronoiCells(*(_to_caller_order(t, row_of) for t in cells))) is True
        if stop_requested or (tol is not None and step.max_displacement < tol):
            break
    current = current.clone() if row_of is None else _to_caller_order(current, row_of)
    return (current, history) if return_history else current


def _to_caller_order(rows: torch.Tensor, row_of: Optional[torch.Tensor]) -> torch.Tensor:
    """A new tensor with ``rows[i]`` at row ``row_of[i]`` (the caller's order;
    ``row_of`` None: already in it)."""
    if row_of is None:
        return rows.clone()
    return torch.empty_like(rows).index_copy_(0, row_of, rows)


def _check_arguments(points, iters, tol, k) -> None:
    if not isinstance(points, torch.Tensor):
        raise TypeError(f"torchvor.lloyd: points must be a torch.Tensor, got {type(points).__name__}")
    if not points.is_floating_point():
        raise TypeError(f"torchvor.lloyd: points must be float32 or float64, got {points.dtype}")
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"torchvor.lloyd: points must have shape (N, 3), got {tuple(points.shape)}")
    if not isinstance(iters, int) or iters < 0:
        raise ValueError(f"torchvor.lloyd: iters must be a non-negative int, got {iters!r}")
    if tol is not None and not tol >= 0:
        raise ValueError(f"torchvor.lloyd: tol must be None or >= 0, got {tol!r}")
    if k is not None and (not isinstance(k, int) or k < 1):
        raise ValueError(f"torchvor.lloyd: k must be None or a positive int, got {k!r}")


def _periodic_step(current: torch.Tensor, pbox, batch: Optional[torch.Tensor], k: Optional[int]):
    """_step's outputs for a periodic box, from a periodic voronoi call (rows
    in the caller's order: `order` is the identity)."""
    n = current.shape[0]
    cells = _periodic.voronoi(current, pbox, batch, k, DEFAULT_MEMORY_BUDGET)
    computed = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
    failed = int((~computed).sum())
    target = torch.where(computed.unsqueeze(1), cells.centroid, current)
    moved = _periodic.wrap(target, pbox, batch)
    energy = float(cells.second_moment.sum(dtype=torch.float64))
    edges = pbox.box[:, 1] - pbox.box[:, 0]
    diagonal = (edges.norm(dim=1)[batch] if batch is not None else edges[0].norm().expand(n)).double()
    max_displacement = float(((target - current).double().norm(dim=1) / diagonal).max()) if n else 0.0
    needed = neighbors_quantile(cells.neighbors_needed[computed])
    return moved, cells, torch.arange(n, device=current.device), energy, max_displacement, k or 0, failed, needed


def neighbors_quantile(neighbors_needed: torch.Tensor) -> int:
    """The K_QUANTILE of the computed cells' neighbour counts (of a strided
    sample of QUANTILE_SAMPLE beyond that many), rounded up; 0 for none."""
    if neighbors_needed.numel() == 0:
        return 0
    counts = neighbors_needed.double()
    return int(math.ceil(float(torch.quantile(counts[:: max(1, counts.numel() // QUANTILE_SAMPLE)], K_QUANTILE))))


def _step(current: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor],
          k: Optional[int]) -> Tuple[torch.Tensor, VoronoiCells, torch.Tensor, float, float, int, int, int]:
    """One Lloyd iteration (``torchvor::lloyd_step``) and what it measured:
    (moved points, cells, order, energy, max displacement / box diagonal,
    the first pass's k (the pilot's where ``k`` is None), failed cells,
    neighbours needed by K_QUANTILE of the cells).

    The cells, the moved points and ``order`` are in the op's grid order: row
    i is the cell of ``current[order[i]]``. The op launches the move, the
    energy (summed in float64: a float32 total blurs the small decrease of
    late iterations), the largest displacement and the histogram of the
    neighbours the cells needed before it waits for the device, and reads
    them to the host with its last status read, so a step waits once. A
    failed cell's NaN second moment makes the energy NaN, and only then are
    the failures counted (a second read). The quantile comes from a histogram
    of at most 2 * QUANTILE_SAMPLE cells spread over the input: its standard
    error is then ~0.05% of the cells, and a histogram of every cell would
    make all of them contend for the ~10 bins their counts fall in.
    """
    count = current.shape[0]
    stride = max(1, count // QUANTILE_SAMPLE)
    # Cells that needed more than HISTOGRAM_BINS neighbours are left out of
    # the histogram; they lie above any quantile it reaches, and if more than
    # 1% do, `needed` comes out as HISTOGRAM_BINS (above MAX_K) because the
    # cumulative count never reaches the rank.
    moved, *outputs, order, measures, histogram = torch.ops.torchvor.lloyd_step.default(
        current, box, batch, k, stride, HISTOGRAM_BINS)
    cells = VoronoiCells(*outputs)
    energy, largest_displacement2, used_k = measures.tolist()
    sample = (count + stride - 1) // stride
    rank = min(sample, max(1, math.ceil(K_QUANTILE * sample)))
    needed = int(np.searchsorted(np.cumsum(histogram.numpy()), rank))  # first bin whose cumulative count reaches rank
    failed = 0
    if not math.isfinite(energy):
        failed = int(((cells.status != CellStatus.SUCCESS) & (cells.status != CellStatus.DUPLICATE)).sum())
    return moved, cells, order, energy, math.sqrt(largest_displacement2), int(used_k), failed, needed


def _adapted_k(neighbors_needed: int) -> int:
    return max(MIN_K, min(MAX_K, neighbors_needed + K_MARGIN))


def _progress_line(step: LloydStep, iters: int) -> str:
    width = len(str(iters))
    failed = f"  failed {step.failed}" if step.failed else ""
    return (f"lloyd {step.iteration + 1:>{width}}/{iters}  energy {step.energy:.6e}  "
            f"max displacement {step.max_displacement:.3e}  k {step.k:>3}  "
            f"{step.seconds:.3f} s{failed}")


__all__ = ["lloyd", "LloydStep"]
