"""Semi-discrete optimal transport: the weights whose power diagram gives every
cell a prescribed volume (:func:`power_weights`), and capacity-constrained
Lloyd relaxation on them (:func:`power_lloyd`).

Damped Newton (Kitagawa, Merigot and Thibert 2019) on the cells of
torchvor/power.py, with the power diagram's Laplacian as the Jacobian (a
sparse CSR matrix of the cells' faces) and conjugate gradients in torch.
"""
from __future__ import annotations

import math
import warnings
from typing import NamedTuple, Optional, Tuple

import torch

from . import power as _power
from .ops import DEFAULT_MEMORY_BUDGET, CellStatus, VoronoiCells
from .power import PowerFaces, check_inputs, check_weights

_EMPTY = int(CellStatus.EMPTY)


class PowerWeights(NamedTuple):
    """Result of :func:`power_weights`.

    weights: (N,) the points' dtype: the power diagram with these weights
        gives every cell its target volume (up to ``error``); their mean is 0
        (adding a constant changes no cell; float32 weights: up to a few ulps
        of the largest, the shift whose rounding errs least).
    iterations: Newton iterations taken.
    error: the largest relative volume error, ``max |V_i - target_i| / target_i``.
    cells: the :class:`VoronoiCells` (power cells) of the returned weights.
    """

    weights: torch.Tensor
    iterations: int
    error: float
    cells: VoronoiCells


class _Jacobian(NamedTuple):
    """The volumes' Jacobian in the weights (d V_i / d w_j = -c_ij, c_ij =
    a_ij / (2 |x_i - x_j|), for each face (j, i); rows summing to zero):
    ``matrix`` the (N, N) CSR matrix, the row sums on its diagonal, so that a
    conjugate-gradient iteration is one sparse product; ``diagonal`` (N,)."""
    matrix: torch.Tensor
    diagonal: torch.Tensor

    @staticmethod
    def of(n: int, edge_index: torch.Tensor, coefficient: torch.Tensor) -> "_Jacobian":
        """From each face (j, i)'s c_ij (repeated pairs add up)."""
        j, i = edge_index
        key, order = torch.sort(i * n + j)
        return _Jacobian._assembled(n, key // n, key % n, coefficient[order])

    @staticmethod
    def of_faces(n: int, faces: PowerFaces, work: torch.Tensor) -> "_Jacobian":
        """From the cells' own faces: c_ij from the mean of the areas listed for
        the pair i, j, as graph_of_faces gives them (one listing where one side
        dropped a sliver), by one sort of the faces' (cell, neighbour) keys and
        their reverses."""
        between = faces.target >= 0
        i, j, area = faces.cell[between], faces.target[between], faces.area[between]
        keys, order = torch.sort(torch.cat([i * n + j, j * n + i]))
        keys, inverse, listings = torch.unique_consecutive(keys, return_inverse=True, return_counts=True)
        total = area.new_zeros(keys.numel()).index_add_(0, inverse, area.repeat(2)[order])
        rows, columns = keys // n, keys % n
        return _Jacobian._assembled(n, rows, columns, total / listings / (2 * (work[rows] - work[columns]).norm(dim=1)))

    @staticmethod
    def _assembled(n: int, rows: torch.Tensor, columns: torch.Tensor, c: torch.Tensor) -> "_Jacobian":
        """The CSR matrix of entries -c at (rows, columns), sorted by row then
        column, and each row's sum of c on its diagonal, in its column's place
        (after any entry of the row's own column, whose terms cancel)."""
        device = c.device
        diagonal = torch.zeros(n, dtype=c.dtype, device=device).index_add(0, rows, c)
        counts = torch.bincount(rows, minlength=n)
        row_start = torch.zeros(n + 1, dtype=torch.int64, device=device)
        row_start[1:] = (counts + 1).cumsum(0)
        # an entry's place: its row's start, its rank in the row, one more past the diagonal
        rank = torch.arange(rows.numel(), device=device) - (counts.cumsum(0) - counts)[rows]
        place = row_start[rows] + rank + (columns >= rows)
        before = torch.zeros(n, dtype=torch.int64, device=device).index_add(0, rows, (columns < rows).long())
        on_diagonal = row_start[:-1] + before
        values = torch.empty(rows.numel() + n, dtype=c.dtype, device=device)
        values[place] = -c
        values[on_diagonal] = diagonal
        column = torch.empty(rows.numel() + n, dtype=torch.int64, device=device)
        column[place] = columns
        column[on_diagonal] = torch.arange(n, device=device)
        with warnings.catch_warnings():  # torch's notices that sparse CSR is in beta, unchecked
            warnings.filterwarnings("ignore", message="Sparse (CSR tensor support|invariant checks)")
            index = torch.int32 if values.numel() < 2**31 else torch.int64  # int32: a lighter product
            matrix = torch.sparse_csr_tensor(row_start.to(index), column.to(index), values, (n, n))
        return _Jacobian(matrix, diagonal)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return self.matrix @ x


# The conjugate gradients test their residual every CG_CHECK iterations (one
# wait for the device each time).
CG_CHECK = 4


def _conjugate_gradient(jacobian: _Jacobian, rhs, rtol: float, max_iters: int):
    """J x = rhs (sum of rhs 0, J a graph Laplacian: x of mean 0) by CG with
    the Jacobi preconditioner, to |r| <= rtol |rhs| (tested every CG_CHECK
    iterations), or until a direction finds no curvature (J's null space,
    by rounding)."""
    diagonal = jacobian.diagonal
    inverse = torch.where(diagonal > 0, 1.0 / diagonal, torch.zeros_like(diagonal))
    x = torch.zeros_like(rhs)
    r = rhs - rhs.mean()
    z = inverse * r
    p = z.clone()
    rz = torch.dot(r, z)
    stop = rtol * float(r.norm())
    stalled = torch.zeros((), dtype=torch.bool, device=rhs.device)
    for iteration in range(max_iters):
        if iteration % CG_CHECK == 0 and bool((r.norm() <= stop) | stalled):
            break
        q = jacobian.apply(p)
        curvature = torch.dot(p, q)
        stalled |= ~(curvature > 0)  # no step once a direction found no curvature
        alpha = torch.where(stalled, 0.0, rz / curvature)
        x.addcmul_(alpha, p)
        r.addcmul_(alpha, q, value=-1)
        torch.mul(inverse, r, out=z)
        rz_next = torch.dot(r, z)
        p = torch.addcmul(z, torch.where(rz > 0, rz_next / rz, 0.0), p)
        rz = rz_next
    return x - x.mean()


def _jacobian(n: int, found, work: torch.Tensor) -> _Jacobian:
    """The volumes' Jacobian in the weights from evaluate's faces: PowerFaces,
    or a periodic call's (edge_index, c)."""
    if not isinstance(found, PowerFaces):
        return _Jacobian.of(n, *found)
    return _Jacobian.of_faces(n, found, work)


def _periodic_faces(graph, work: torch.Tensor, period: torch.Tensor):
    """(edge_index, c) of a periodic voronoi_graph (cells, edge_index, area,
    centroid, wall_area, shift): c = area / (2 |x_i - image of x_j|); a
    cell's faces with its own images do not move with its weight."""
    _cells, edge_index, area, _centroid, _walls, shift = graph
    j, i = edge_index
    keep = i != j
    j, i = j[keep], i[keep]
    across = work[j] + shift[keep].double() * period - work[i]
    return torch.stack([j, i]), area[keep] / (2 * across.norm(dim=1))


# power_weights' trial steps at a largest relative error over SAMPLE_ERROR are
# first computed on every SAMPLE_STRIDE-th cell (clouds of SAMPLE_MIN_POINTS
# and more): a step refused there costs the sample's cells, not all of them.
SAMPLE_ERROR = 0.1
SAMPLE_STRIDE = 16
SAMPLE_MIN_POINTS = 20_000
# Float32 points' cells and faces are computed in float32 from zero weights and
# for the trial steps from a largest relative error over SINGLE_ERROR: there
# their rounding is noise far below the error, and the steps after them land
# far above it.
SINGLE_ERROR = 0.2
# Float32 points' Newton stops once its float64 error is below ROUNDING_SHARE
# of what rounding the weights to float32 adds (the Jacobian times the
# rounding): further steps cannot lower the error of the weights returned.
# The rounding is the best of ROUNDING_SHIFTS (_float32_weights).
ROUNDING_SHARE = 0.25
ROUNDING_SHIFTS = 8


def _faces_in_float64(gather):
    """The faces' gather (power_cells' faces="later"), their floating columns in float64."""
    def gathered() -> PowerFaces:
        found = gather()
        return PowerFaces(found.cell, found.target, found.area.double(), found.centroid.double(),
                          found.inertia.double())
    return gathered


def _float32_weights(jacobian: _Jacobian, weights: torch.Tensor, target: torch.Tensor) -> Tuple[torch.Tensor, float]:
    """(float32 weights, the largest relative volume error their rounding adds,
    to first order: the Jacobian times the rounding) of float64 `weights` of
    mean 0: of the weights plus each of ROUNDING_SHIFTS constants (steps of
    0.382 of the largest weight's ulp: each rounds the weights apart), the
    one that adds the least."""
    ulp = float(torch.finfo(torch.float32).eps) * float(weights.abs().max())
    candidates = [(weights + k * 0.3819660112501051 * ulp).float() for k in range(ROUNDING_SHIFTS)]
    errors = torch.stack([(jacobian.apply(c.double() - weights).abs() / target).max() for c in candidates])
    best = int(torch.argmin(errors))
    return candidates[best], float(errors[best])


def _rounding_decides(jacobian: _Jacobian, weights: torch.Tensor, target: torch.Tensor, error: float) -> bool:
    """Whether `error` is under ROUNDING_SHARE of what the best rounding of the
    weights to float32 adds (_float32_weights), tested first on the plain
    rounding's (no less: one sparse product)."""
    plain = float((jacobian.apply(weights.float().double() - weights).abs() / target).max())
    return error <= ROUNDING_SHARE * plain and error <= ROUNDING_SHARE * _float32_weights(jacobian, weights, target)[1]


def power_weights(points: torch.Tensor, box=None, *, volumes: Optional[torch.Tensor] = None, tol: float = 1e-6,
                  max_iters: int = 100, k: Optional[int] = None, progress: bool = False,
                  memory_budget: int = DEFAULT_MEMORY_BUDGET, weights: Optional[torch.Tensor] = None,
                  periodic=False) -> PowerWeights:
    """Weights whose power diagram gives every cell a prescribed volume
    (semi-discrete optimal transport of the uniform measure on the box to the
    points).

    Damped Newton (Kitagawa, Merigot and Thibert 2019): from zero weights
    (the Voronoi diagram), each step solves ``J dw = target - V`` by
    conjugate gradients, J the power diagram's Laplacian (``d V_i / d w_j =
    -a_ij / (2 |x_i - x_j|)``, a_ij the face area), and halves the step until
    no cell shrinks below half the smallest initial or target volume and the
    largest volume error falls by at least a factor ``1 - step / 2`` (far
    from the solution, a trial step is first computed on every 16th cell,
    which can refuse it). The cells are computed in float64, but far from the
    solution (a largest error over 0.2, and from zero weights) float32
    points' cells and faces are computed in float32.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``,
            distinct (a copy of a point can get no volume of its own).
        box: as :func:`torchvor.voronoi`.
        volumes: (N,) positive target volumes in proportion (scaled to sum
            to the box's volume), the points' dtype and device; default: all
            equal.
        tol: the largest relative volume error to reach, ``> 0``.
        max_iters: Newton iterations at most; not converged then: a
            RuntimeWarning, and the weights reached. Float32 weights are
            the float64 solution rounded: their cells and ``error`` are those
            of the rounded weights (the rounding leaves errors that grow with
            the weights' spread and N: about 1e-5 at 100K white-noise points,
            3e-5 at 1M, whatever ``tol``), and Newton stops once its float64
            error is under a quarter of what the rounding adds.
        k: with ``periodic``, as :func:`torchvor.voronoi` (the plain cells
            that size the padding); unused otherwise (power cells walk a
            grid of the points, no neighbour lists).
        progress: print each iteration's error and step.
        memory_budget: bytes of the faces that one pass computes at a time.
        weights: (N,) the weights to start from (default zeros: the Voronoi
            diagram), e.g. the previous solution of points that moved a little;
            halved towards zero while it empties a cell.
        periodic: as :func:`torchvor.voronoi` (the box required): the power
            diagram on the torus, whose cells share the box's volume.

    Returns:
        :class:`PowerWeights` ``(weights, iterations, error, cells)``.

    Raises:
        ValueError: bad shapes or values (as :func:`torchvor.voronoi`),
            non-positive volumes or tol, duplicate points.
        TypeError: mismatched dtypes.
        RuntimeError: a cell that could not be computed.
    """
    from . import periodic as _periodic
    from .ops import _box_for_call, _check_points, _check_tensor

    _check_tensor(points, "points")
    axes = _periodic.periodic_axes(periodic, "power_weights")
    if axes is None:
        box_tensor = _box_for_call(points, box, None)
        check_inputs(points, box_tensor, None)
    else:
        _check_points(points, "power_weights")
        box_tensor = _periodic.periodic_box(points, box, None, axes, "power_weights").box
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"torchvor.power_weights: tol must be a positive number, got {tol!r}")
    if not (isinstance(max_iters, int) and max_iters >= 0):
        raise ValueError(f"torchvor.power_weights: max_iters must be a non-negative int, got {max_iters!r}")
    n = points.shape[0]
    if box_tensor.shape[0] != 1:
        raise ValueError("torchvor.power_weights: one box, (lo, hi) or (2, 3)")
    lo, hi = box_tensor[0, 0].double(), box_tensor[0, 1].double()
    box_volume = float((hi - lo).prod())
    if volumes is None:
        target = torch.full((n,), box_volume / max(n, 1), dtype=torch.float64, device=points.device)
    else:
        target = check_weights(points, volumes, "power_weights").double()
        if n and not bool((target > 0).all()):
            raise ValueError("torchvor.power_weights: volumes must be positive")
        target = target * (box_volume / float(target.sum())) if n else target
    work = points.double().contiguous()
    box64 = box_tensor.double()
    pbox = None if axes is None else _periodic.periodic_box(work, box64, None, axes, "power_weights")
    rounds = points.dtype == torch.float32  # float32 weights returned, rounded from float64 ones
    single = rounds and pbox is None  # float32 cells far from the solution
    cold = weights is None
    if weights is None:
        weights = torch.zeros(n, dtype=torch.float64, device=points.device)
    else:
        weights = check_weights(points, weights, "power_weights").double()
        weights = weights - weights.mean() if n else weights
    if n == 0:
        cells, _ = _power.power_cells(points, weights.to(points.dtype), box_tensor, None, memory_budget)
        return PowerWeights(weights.to(points.dtype), 0, 0.0, cells)

    hint = None  # the last cells' radii

    def evaluate(w, faces, in_float32=False):
        """(cells, faces for _jacobian (or the function that computes them) or None,
        volumes (float64)): the power diagram of weights w, `in_float32` of the
        float32 points and weights (their cells and faces in float32 where
        they pass its checks)."""
        nonlocal hint
        if in_float32:
            cells, found = _power.power_cells(points, w.float(), box_tensor, None, memory_budget, faces=faces and "later",
                                       radius_hint=hint, float32_faces=True)
            found = _faces_in_float64(found) if found is not None else None
            hint = cells.radius
        elif pbox is None:
            # faces gathered only for the Jacobian of a step taken and not the last
            cells, found = _power.power_cells(work, w, box64, None, memory_budget, faces=faces and "later", radius_hint=hint)
            hint = cells.radius
        elif faces:
            graph = _periodic.voronoi_graph(work, pbox, None, k, memory_budget, w)
            cells, found = graph[0], _periodic_faces(graph, work, pbox.period[0])
        else:
            cells, found = _periodic.voronoi(work, pbox, None, k, memory_budget, weights=w), None
        code = cells.status
        failed = (code != int(CellStatus.SUCCESS)) & (code != _EMPTY)
        if bool(failed.any()):
            if bool((code == int(CellStatus.DUPLICATE)).any()):
                raise ValueError("torchvor.power_weights: points must be distinct (exact copies found)")
            first = int(torch.nonzero(failed)[0])
            raise RuntimeError(f"torchvor.power_weights: the power cell of point {first} could not be computed "
                               f"(status {CellStatus(int(code[first])).name})")
        volume = torch.where(code == _EMPTY, torch.zeros_like(cells.volume), cells.volume).double()
        return cells, found, volume

    # A trial step far from the solution (where steps are halved) is first
    # tried on a sample of the cells: one that fails there fails on all of them.
    sample = (torch.arange(0, n, SAMPLE_STRIDE, device=points.device)
              if pbox is None and n >= SAMPLE_MIN_POINTS else None)

    def sample_refuses(w, least, most, in_float32) -> bool:
        """Whether the sampled cells of weights w (`in_float32` as evaluate)
        already hold a volume below `least` or an error over `most` (a cell
        not computed refuses nothing: the whole evaluation reports it)."""
        if in_float32:
            found, _ = _power.power_cells(points, w.float(), box_tensor, None, memory_budget, rows=sample, radius_hint=hint)
        else:
            found, _ = _power.power_cells(work, w, box64, None, memory_budget, rows=sample, radius_hint=hint)
        code = found.status[sample]
        sampled = torch.where(code == _EMPTY, torch.zeros_like(found.volume[sample]), found.volume[sample]).double()
        refused = (sampled.min() < least) | ((sampled - target[sample]).abs().max() > most)
        return bool(refused & ((code == int(CellStatus.SUCCESS)) | (code == _EMPTY)).all())

    # zero weights' error is unknown (float32 if SINGLE_ERROR allows any); a warm start's is small
    cells, faces, volume = evaluate(weights, True, single and cold and SINGLE_ERROR < math.inf)
    # Newton needs every cell nonempty (its Jacobian is then a connected graph's
    # Laplacian): a start that empties a cell is halved towards zero weights
    # (the Voronoi diagram), whose cells are all nonempty.
    for _halving in range(60):
        if bool((volume > 0).all()):
            break
        weights = weights / 2 if _halving < 59 else torch.zeros_like(weights)
        cells, faces, volume = evaluate(weights, True)
    floor = 0.5 * min(float(volume.min()), float(target.min()))
    error = float(((volume - target).abs() / target).max())
    iterations = 0
    jacobian = None  # of the current weights' faces, once built
    converged = error <= tol
    while not converged and iterations < max_iters:
        if callable(faces):
            faces = faces()
        jacobian = _jacobian(n, faces, work)
        if rounds and _rounding_decides(jacobian, weights, target, error):
            if progress:
                print(f"power_weights: error {error:.3e}, under a quarter of what rounding the weights to "
                      "float32 adds: stopped")
            converged = True
            break
        iterations += 1
        # inexact Newton: the step's residual need only fall with the error, and
        # no further than a hundredth of what tol leaves
        step = _conjugate_gradient(jacobian, target - volume, min(1e-2, max(0.1 * error, 0.01 * tol / error)),
                                   10 * n + 100)
        worst = float((volume - target).abs().max())
        in_float32 = single and error > SINGLE_ERROR
        tau = 1.0
        while True:
            trial = weights + tau * step
            if (sample is None or error <= SAMPLE_ERROR
                    or not sample_refuses(trial, floor, (1 - tau / 2) * worst, in_float32)):
                trial_cells, trial_faces, trial_volume = evaluate(trial, True, in_float32)
                trial_worst = float((trial_volume - target).abs().max())
                if float(trial_volume.min()) >= floor and trial_worst <= (1 - tau / 2) * worst:
                    break
            tau /= 2
            if tau < 1e-12:
                raise RuntimeError("torchvor.power_weights: Newton's step found no descent (the cells are "
                                   "ill-conditioned)")
        weights = trial - trial.mean()
        cells, faces, volume = trial_cells, trial_faces, trial_volume
        error = float(((volume - target).abs() / target).max())
        converged = error <= tol
        if progress:
            print(f"power_weights: iteration {iterations}: error {error:.3e}, step {tau:g}")
    if not converged:
        warnings.warn(f"torchvor.power_weights: not converged after {iterations} iterations "
                      f"(error {error:.3e} > tol {tol:.1e})", RuntimeWarning, stacklevel=2)
    if rounds:  # the cells and the error of the weights as rounded
        if jacobian is None:
            jacobian = _jacobian(n, faces() if callable(faces) else faces, work)
        # (the last step's Jacobian: the weights moved by less than its error since)
        result, _ = _float32_weights(jacobian, weights, target)
        cells, _, volume = evaluate(result.double(), False)
        error = float(((volume - target).abs() / target).max())
    else:
        result = weights
    result_cells = VoronoiCells(*(t.to(points.dtype) if t.dtype == torch.float64 else t for t in cells))
    return PowerWeights(result, iterations, error, result_cells)


def power_lloyd(points: torch.Tensor, box=None, iters: int = 10, *, volumes: Optional[torch.Tensor] = None,
                tol: float = 1e-6, k: Optional[int] = None, progress: bool = False,
                move_tol: Optional[float] = None, periodic=False) -> Tuple[torch.Tensor, torch.Tensor]:
    """Capacity-constrained Lloyd relaxation (de Goes et al. 2012, blue noise
    through optimal transport): each iteration solves the weights that give
    every cell its target volume (:func:`power_weights`, warm-started from the
    previous ones), then moves every point to its power cell's centroid.

    Args:
        points: (N, 3) float32 or float64, distinct, inside ``box``. Not modified.
        box: as :func:`torchvor.voronoi` (one box).
        iters: iterations (>= 0).
        volumes: (N,) target volumes in proportion (default: all equal).
        tol: :func:`power_weights`' tolerance at each iteration.
        k: as :func:`torchvor.voronoi`.
        progress: print each iteration's Newton iterations and error.
        move_tol: stop early once an iteration moves no point farther than
            this times the box's diagonal (None: run all ``iters``).
        periodic: as :func:`torchvor.voronoi` (the box required): the points
            move on the torus, wrapped into the box.

    Returns:
        ``(points, weights)``: the moved points, (N, 3) in the input's dtype,
        and the weights of their last power diagram (before the last move).
    """
    from . import periodic as _periodic
    from .ops import _box_for_call, _check_points, _check_tensor

    _check_tensor(points, "points")
    if not (isinstance(iters, int) and iters >= 0):
        raise ValueError(f"torchvor.power_lloyd: iters must be a non-negative int, got {iters!r}")
    axes = _periodic.periodic_axes(periodic, "power_lloyd")
    pbox = None
    if axes is None:
        box_tensor = _box_for_call(points, box, None)
        check_inputs(points, box_tensor, None)
    else:
        _check_points(points, "power_lloyd")
        pbox = _periodic.periodic_box(points.detach(), box, None, axes, "power_lloyd")
        box_tensor = pbox.box
    lo, hi = box_tensor[0, 0], box_tensor[0, 1]
    current = points.detach().clone() if pbox is None else _periodic.wrap(points.detach(), pbox, None).clone()
    weights = None
    for iteration in range(iters):
        solved = power_weights(current, box_tensor[0], volumes=volumes, tol=tol, k=k, weights=weights,
                               periodic=periodic)
        weights = solved.weights
        moved = solved.cells.centroid
        if progress:
            print(f"power_lloyd: iteration {iteration}: {solved.iterations} Newton iterations, "
                  f"error {solved.error:.2e}")
        # every cell holds its target volume (> 0), so every centroid is finite; clamp rounding
        moved = torch.minimum(torch.maximum(moved, lo), hi) if pbox is None else _periodic.wrap(moved, pbox, None)
        if pbox is not None:  # wrapped across a face: the move is the step, not the jump
            step = _periodic.minimum_image(moved.double() - current.double(), pbox.period[0].double())
        else:
            step = moved.double() - current.double()
        largest_move = float(step.norm(dim=1).max()) if len(current) else 0.0
        current = moved
        if move_tol is not None and largest_move <= move_tol * float((hi - lo).double().norm()):
            break
    if weights is None:
        weights = torch.zeros(points.shape[0], dtype=points.dtype, device=points.device)
    return current, weights
