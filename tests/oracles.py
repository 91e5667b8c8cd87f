"""Independent reference implementations for torchvor's tests.

Nothing here calls torchvor: the kNN oracle is brute force in float64 (numpy),
and the Voronoi oracle intersects half-spaces with scipy/Qhull, cell by cell,
using the bisectors of *all* other points plus the six box planes; single
cells can also be computed in exact rational arithmetic (exact_cell_oracle).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Optional, Sequence

import numpy as np

__all__ = [
    "brute_force_knn",
    "pairwise_dist2",
    "exact_knn_with_ties",
    "check_knn_result",
    "tetrahedron_integrals",
    "CellOracle",
    "voronoi_cell_oracle",
    "voronoi_oracle",
    "exact_cell_oracle",
]


# ----------------------------------------------------------------------------- kNN


def _np64(x) -> np.ndarray:
    """Any tensor / array -> float64 numpy array holding exactly the same values."""
    if hasattr(x, "detach"):
        x = x.detach().cpu()
        if x.dtype.is_floating_point:
            x = x.double()
        x = x.numpy()
    return np.asarray(x, dtype=np.float64)


def pairwise_dist2(queries, points) -> np.ndarray:
    """(M, N) squared distances in float64 from explicit coordinate differences
    (no |a|^2 - 2ab + |b|^2 expansion, which cancels catastrophically at large offsets)."""
    q = _np64(queries)
    p = _np64(points)
    out = np.zeros((q.shape[0], p.shape[0]))
    for a in range(3):
        diff = q[:, a, None] - p[None, :, a]
        out += diff * diff
    return out


def distances_separated(points, queries, gap: float = 2e-5, radius: Optional[float] = None) -> bool:
    """Whether each query's (and each point's) squared distances to the
    points differ pairwise by more than `gap`, and from radius^2 where given:
    gradcheck's finite differences (1e-6 a coordinate) then never reorder a
    neighbour list or move a pair across the radius, where dist2 jumps."""
    for q in (points, queries):
        d2 = np.sort(pairwise_dist2(q, points), axis=1)
        if np.any(np.diff(d2, axis=1) <= gap) or (radius is not None and np.any(np.abs(d2 - radius**2) <= gap)):
            return False
    return True


def _np_batch(b) -> Optional[np.ndarray]:
    if b is None:
        return None
    return np.asarray(b.detach().cpu() if hasattr(b, "detach") else b, dtype=np.int64)


def _allowed(rows: np.ndarray, n: int, batch, query_batch, exclude_self: bool) -> np.ndarray:
    """(len(rows), n) mask of the points query `rows[r]` may return."""
    allowed = np.ones((len(rows), n), dtype=bool)
    if batch is not None:
        allowed &= query_batch[rows, None] == batch[None, :]
    if exclude_self:
        allowed[np.arange(len(rows)), rows] = False
    return allowed


def _normalise(points, queries, batch, query_batch, exclude_self):
    if queries is None:
        queries = points
        exclude_self = True if exclude_self is None else exclude_self
        if query_batch is None:
            query_batch = batch
    return queries, _np_batch(batch), _np_batch(query_batch), bool(exclude_self)


def _chunks(m: int, n: int):
    step = max(1, (1 << 22) // max(n, 1))
    for begin in range(0, m, step):
        yield np.arange(begin, min(m, begin + step))


def brute_force_knn(points, k: int, queries=None, *, batch=None, query_batch=None,
                    exclude_self: Optional[bool] = None):
    """Reference kNN in float64: (dist2 (M, k) float64, idx (M, k) int64), sorted by
    (distance, index), padded with (inf, -1). Same conventions as torchvor.knn
    (queries=None: the points, excluding themselves unless exclude_self=False)."""
    queries, batch, query_batch, exclude_self = _normalise(points, queries, batch, query_batch,
                                                           exclude_self)
    p, q = _np64(points), _np64(queries)
    n, m = len(p), len(q)
    dist = np.full((m, k), np.inf)
    idx = np.full((m, k), -1, dtype=np.int64)
    kk = min(k, n)
    for rows in _chunks(m, n):
        d2 = pairwise_dist2(q[rows], p)
        d2[~_allowed(rows, n, batch, query_batch, exclude_self)] = np.inf
        if kk == 0:
            continue
        # the kk smallest by (distance, index): all below the kk-th distance, then
        # the lowest indices among those equal to it
        thr = np.partition(d2, kk - 1, axis=1)[:, kk - 1:kk]
        below = d2 < thr
        equal = d2 == thr
        need = kk - below.sum(1, keepdims=True)
        chosen = below | (equal & (np.cumsum(equal, 1) <= need))
        cand = np.nonzero(chosen)[1].reshape(len(rows), kk)  # increasing index per row
        dd = np.take_along_axis(d2, cand, 1)
        order = np.take_along_axis(cand, np.argsort(dd, axis=1, kind="stable"), 1)
        dd = np.take_along_axis(d2, order, 1)
        ii = order.astype(np.int64)
        ii[~np.isfinite(dd)] = -1
        dist[rows, :kk] = dd
        idx[rows, :kk] = ii
    return dist, idx


def exact_knn_with_ties(points, k: int, queries=None, **kwargs):
    """Alias of :func:`brute_force_knn` for inputs whose squared distances are exact
    in the tested dtype (e.g. small integer coordinates): then (distance, index)
    order is unique and a result must match it index for index, distance for distance."""
    return brute_force_knn(points, k, queries, **kwargs)


def check_knn_result(dist2, idx, points, k: int, queries=None, *, batch=None, query_batch=None,
                     exclude_self: Optional[bool] = None, rtol: Optional[float] = None) -> None:
    """Tie-aware comparison of a kNN result (tensors) with the float64 brute force.

    * shapes (M, k), idx int64, dist2 of the points' dtype;
    * every returned index is valid (in range, allowed batch element, not the
      excluded self, not repeated in its row), and its true float64 distance
      equals the returned dist2 up to the rounding of the points' dtype;
    * rows are sorted by (dist2, idx); padding (inf, -1) exactly where the oracle
      has fewer than k candidates, and only at the end of a row;
    * the true distances of the returned indices, sorted, equal the oracle's k
      smallest (by value, so equidistant points may be exchanged).
    Raises AssertionError describing the first mismatching query.
    """
    if queries is None and query_batch is None:
        query_batch = batch
    queries, batch_np, qbatch_np, excl = _normalise(points, queries, batch, query_batch, exclude_self)
    is_float32 = str(dist2.dtype) == "torch.float32"
    if rtol is None:
        # fl(a - b) and 3 roundings per squared distance: < 8 units of roundoff
        rtol = 8 * 2.0 ** -24 if is_float32 else 8 * 2.0 ** -53
    m, n = queries.shape[0], points.shape[0]
    assert tuple(dist2.shape) == (m, k), f"dist2 shape {tuple(dist2.shape)} != {(m, k)}"
    assert tuple(idx.shape) == (m, k), f"idx shape {tuple(idx.shape)} != {(m, k)}"
    assert str(idx.dtype) == "torch.int64", f"idx dtype {idx.dtype}"
    assert dist2.dtype == points.dtype, f"dist2 dtype {dist2.dtype} != points dtype {points.dtype}"
    assert dist2.device == points.device and idx.device == points.device, "outputs on the wrong device"
    got_d = _np64(dist2)
    got_i = idx.detach().cpu().numpy()
    ref_d, ref_i = brute_force_knn(points, k, queries, batch=batch, query_batch=query_batch,
                                   exclude_self=excl)
    p, q = _np64(points), _np64(queries)

    def fail(rows, message):
        r = int(rows[0])
        raise AssertionError(f"query {r}: {message}\n  got idx  {got_i[r]}\n  got d2   {got_d[r]}"
                             f"\n  oracle   {ref_i[r]}\n  oracle d2 {ref_d[r]}")

    valid = got_i >= 0
    bad = np.nonzero(valid.sum(1) != np.isfinite(ref_d).sum(1))[0]
    if len(bad):
        fail(bad, "wrong number of neighbours (padding)")
    bad = np.nonzero((~valid[:, :-1] & valid[:, 1:]).any(1))[0]
    if len(bad):
        fail(bad, "padding (-1) before a real neighbour")
    bad = np.nonzero((~valid & ~(np.isposinf(got_d))).any(1))[0]
    if len(bad):
        fail(bad, "padding distance is not +inf")
    bad = np.nonzero((valid & ~np.isfinite(got_d)).any(1))[0]
    if len(bad):
        fail(bad, "non-finite distance for a real neighbour")
    bad = np.nonzero((got_i >= n).any(1) | (got_i < -1).any(1))[0]
    if len(bad):
        fail(bad, "index out of range")
    # sorted by (dist2, idx) among the real neighbours; no index repeated
    both = valid[:, :-1] & valid[:, 1:]
    d0, d1, i0, i1 = got_d[:, :-1], got_d[:, 1:], got_i[:, :-1], got_i[:, 1:]
    unsorted = both & ~((d0 < d1) | ((d0 == d1) & (i0 < i1)))
    bad = np.nonzero(unsorted.any(1))[0]
    if len(bad):
        fail(bad, "row not sorted by (dist2, idx)")
    srt = np.sort(np.where(valid, got_i, -1 - np.arange(k)), 1)
    bad = np.nonzero((srt[:, 1:] == srt[:, :-1]).any(1))[0]
    if len(bad):
        fail(bad, "an index appears twice")
    safe = np.where(valid, got_i, 0)
    for rows in _chunks(m, 64):
        allowed = _allowed(rows, n, batch_np, qbatch_np, excl)
        ok = np.take_along_axis(allowed, safe[rows], 1) | ~valid[rows]
        bad = rows[~ok.all(1)]
        if len(bad):
            fail(bad, "returned a forbidden index (other batch element, or the query itself)")
    # true distances of the returned indices
    diff = q[:, None, :] - p[safe]
    true = np.where(valid, np.einsum("mkc,mkc->mk", diff, diff), np.inf)
    fin = valid
    err = np.abs(np.where(fin, got_d, 0.0) - np.where(fin, true, 0.0))
    bad = np.nonzero((err > rtol * np.where(fin, true, 0.0)).any(1))[0]
    if len(bad):
        fail(bad, f"returned dist2 differs from the true distance of the returned index by "
                  f"{err[bad[0]].max():.3e} (rtol {rtol:.1e})")
    true_sorted = np.sort(true, 1)
    close = np.isclose(true_sorted, ref_d, rtol=2 * rtol, atol=0.0) | (np.isinf(true_sorted) & np.isinf(ref_d))
    bad = np.nonzero(~close.all(1))[0]
    if len(bad):
        fail(bad, "returned neighbours are not the k nearest (true distances differ from the oracle's)")


# ------------------------------------------------------------------------- Voronoi


def tetrahedron_integrals(p0, p1, p2, p3, dtype=np.float64):
    """Exact integrals over the tetrahedra (p0, p1, p2, p3), coordinates relative
    to the reference point x_i (arrays of shape (T, 3)), computed in `dtype`.

    Returns (volume (T,), first moment (T, 3), second moment (T,)): the second
    moment is the integral of |x|^2, = vol / 20 * (sum_j |p_j|^2 + |sum_j p_j|^2).
    Volumes are unsigned.
    """
    p0, p1, p2, p3 = (np.asarray(p, dtype=dtype).reshape(-1, 3) for p in (p0, p1, p2, p3))
    vol = np.abs(np.einsum("ij,ij->i", p1 - p0, np.cross(p2 - p0, p3 - p0))) / 6.0
    total = p0 + p1 + p2 + p3
    first = vol[:, None] * total / 4.0
    squares = sum(np.einsum("ij,ij->i", p, p) for p in (p0, p1, p2, p3))
    second = vol / 20.0 * (squares + np.einsum("ij,ij->i", total, total))
    return vol, first, second


@dataclass
class CellOracle:
    volume: float
    centroid: np.ndarray  # (3,) absolute coordinates
    second_moment: float  # integral over the cell of |x - seed|^2
    vertices: np.ndarray  # (V, 3) absolute coordinates
    facet_neighbors: np.ndarray  # indices of the points whose bisector bounds a facet
    seed: np.ndarray  # (3,) the point itself
    duplicate: bool = False
    area: float = 0.0  # surface area of the cell
    # face areas and centroids (absolute), by the point across (>= 0) or the wall (-1 - w)
    faces: Optional[dict] = None
    # the largest |vertex - seed|, from the vertices relative to the seed: the absolute
    # vertices are rounded to the coordinates' spacing, as large as a cell of points a few
    # ulps apart (None: from the absolute vertices)
    relative_radius: Optional[float] = None
    empty: bool = False  # a power cell that no point of the box belongs to

    @property
    def radius(self) -> float:
        """Largest distance from the seed to a vertex of the cell."""
        if self.relative_radius is not None:
            return self.relative_radius
        if len(self.vertices) == 0:
            return 0.0
        return float(np.sqrt(((self.vertices - self.seed) ** 2).sum(1).max()))


def _interior_point(halfspaces: np.ndarray) -> np.ndarray:
    """Chebyshev centre of {x : A x + b <= 0} (rows of A normalised)."""
    from scipy.optimize import linprog

    a, b = halfspaces[:, :3], halfspaces[:, 3]
    norm = np.linalg.norm(a, axis=1)
    c = np.array([0.0, 0.0, 0.0, -1.0])
    res = linprog(c, A_ub=np.hstack([a, norm[:, None]]), b_ub=-b,
                  bounds=[(None, None)] * 3 + [(0, None)], method="highs")
    if not res.success or res.x[3] <= 0:
        raise RuntimeError(f"oracle: empty or flat cell (linprog: {res.message})")
    return res.x[:3]


def _refined_vertices(hs: np.ndarray, intersections: np.ndarray, facets) -> np.ndarray:
    """Each of Qhull's vertices solved again, by least squares (an SVD, as
    numpy's lstsq), on the planes Qhull says meet there; Qhull's own where the
    solution is not finite. Vertices of three planes are solved together."""
    verts = np.array(intersections, dtype=np.float64)
    sizes = np.fromiter((len(f) for f in facets), dtype=np.int64, count=len(facets))
    three = np.nonzero(sizes == 3)[0]
    if len(three):
        planes = hs[np.array([facets[v] for v in three], dtype=np.int64)]  # (m, 3, 4)
        u, s, vh = np.linalg.svd(planes[:, :, :3])
        keep = s > np.finfo(np.float64).eps * 3 * s[:, :1]  # lstsq's rcond=None cut-off
        coef = np.where(keep, np.einsum("mji,mj->mi", u, -planes[:, :, 3]) / np.where(keep, s, 1.0), 0.0)
        sol = np.einsum("mji,mj->mi", vh, coef)
        good = np.all(np.isfinite(sol), axis=1)
        verts[three[good]] = sol[good]
    for v in np.nonzero(sizes != 3)[0]:
        planes = hs[list(facets[v])]
        sol, *_ = np.linalg.lstsq(planes[:, :3], -planes[:, 3], rcond=None)
        if np.all(np.isfinite(sol)):
            verts[v] = sol
    return verts


def _face_fans(verts: np.ndarray, vertex_of: np.ndarray, plane_of: np.ndarray, normals: np.ndarray,
               with_planes: bool = False):
    """Triangles (F, 3, 3) covering the cell's boundary (and, with_planes, the
    plane (F,) of each): each face's vertices
    (those on its plane: the incidences vertex_of[j] on plane_of[j], each
    once) in angular order around the face's mean, fanned.
    Built from the plane incidences rather than a convex hull of the vertices:
    Qhull's hull of a needle cell's vertices can stop with a precision error."""
    planes, group, counts = np.unique(plane_of, return_inverse=True, return_counts=True)
    group = group.reshape(-1)
    normal = normals[planes] / np.linalg.norm(normals[planes], axis=1, keepdims=True)
    axis = np.eye(3)[np.argmin(np.abs(normal), axis=1)]  # the axis least aligned with each normal
    u = np.cross(normal, axis)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    w = np.cross(normal, u)
    mean = np.zeros((len(planes), 3))
    np.add.at(mean, group, verts[vertex_of])
    mean /= counts[:, None]
    offsets = verts[vertex_of] - mean[group]
    angle = np.arctan2(np.einsum("ij,ij->i", offsets, w[group]), np.einsum("ij,ij->i", offsets, u[group]))
    order = np.lexsort((angle, group))  # by face, then around it
    ring, face = vertex_of[order], group[order]
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    local = np.arange(len(ring)) - start[face]
    fan = np.nonzero((local >= 1) & (local <= counts[face] - 2))[0]  # faces of fewer than 3 vertices give none
    triangles = np.stack([verts[ring[start[face[fan]]]], verts[ring[fan]], verts[ring[fan + 1]]], axis=1)
    return (triangles, planes[face[fan]]) if with_planes else triangles


def voronoi_cell_oracle(points, i: int, box, weights=None) -> CellOracle:
    """Voronoi cell of points[i] clipped to box = (lo, hi), by Qhull half-space
    intersection in coordinates relative to the seed (so large offsets lose no
    precision), using the bisectors of all other points and the 6 box planes.
    With `weights` (N,), the power cell: x . r <= (|r|^2 + w_i - w_j) / 2
    relative to the seed; an empty one (no interior point, by linprog) has
    volume 0, centroid the seed and `empty` set; a copy of the seed with a
    larger weight empties it.

    Volume and first moment come from tetrahedra (interior point, hull
    triangle); the second moment about the seed from the same tetrahedra
    with the exact formula vol / 20 * (sum |p_j|^2 + |sum p_j|^2), coordinates
    relative to the seed. Exact duplicates: the lowest index owns the cell,
    higher copies get an empty cell (volume 0, centroid = the seed).
    """
    from scipy.spatial import HalfspaceIntersection, QhullError

    pts = _np64(points)
    lo, hi = (_np64(b).reshape(3) for b in box)
    seed = pts[i]
    rel = pts - seed
    r2 = np.einsum("ij,ij->i", rel, rel)
    index = np.arange(len(pts))
    copies = (r2 == 0) & (index != i)
    w = None if weights is None else _np64(weights).reshape(-1)
    if w is not None and np.any(copies & (w > w[i])):
        return CellOracle(0.0, seed.copy(), 0.0, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), seed, empty=True)
    if np.any(copies & (index < i) & (True if w is None else w == w[i])):
        return CellOracle(0.0, seed.copy(), 0.0, np.zeros((0, 3)), np.zeros(0, dtype=np.int64),
                          seed, duplicate=True)
    use = (index != i) & (r2 > 0)
    owner = np.concatenate([np.full(6, -1), index[use]])  # point index of each half-space
    r = rel[use]
    norm = np.sqrt(r2[use])
    # bisector: x . r <= |r|^2 / 2  ->  (r/|r|) . x - |r|/2 <= 0 (power: |r|^2 + w_i - w_j)
    reach = r2[use] if w is None else r2[use] + w[i] - w[use]
    bis = np.hstack([r / norm[:, None], -0.5 * (reach / norm)[:, None]])
    lo_r, hi_r = lo - seed, hi - seed
    eye = np.eye(3)
    box_hs = np.vstack([np.hstack([-eye, lo_r[:, None]]),   # -x + lo <= 0
                        np.hstack([eye, -hi_r[:, None]])])  # x - hi <= 0
    hs = np.vstack([box_hs, bis])
    scale = float(np.max(hi_r - lo_r))
    # the seed (origin) is interior unless it lies (nearly) on the box or a bisector
    interior = np.zeros(3)
    if w is not None:
        try:
            interior = _interior_point(hs)
        except RuntimeError:  # no interior point: the power cell is empty
            return CellOracle(0.0, seed.copy(), 0.0, np.zeros((0, 3)), np.zeros(0, dtype=np.int64), seed,
                              empty=True)
    elif (-hs[:, 3]).min() <= 1e-6 * scale:
        interior = _interior_point(hs)
    try:
        hsi = HalfspaceIntersection(hs, interior)
    except QhullError:
        # Bisectors of a tight cluster meet at angles near 1e-6; Qhull can
        # then flag a wide facet in post-processing. Allow it: the vertices
        # are refined on their planes below anyway.
        hsi = HalfspaceIntersection(hs, interior, qhull_options="Q12 Pp")
    # refine every vertex by least squares on the planes Qhull says meet there
    facets = [list(f) for f in hsi.dual_facets]
    verts = _refined_vertices(hs, hsi.intersections, facets)
    # merge coinciding vertices (a degenerate vertex comes once per plane triple)
    key = np.round(verts / (1e-11 * scale)).astype(np.int64)
    _, first, group = np.unique(key, axis=0, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    verts = verts[first]
    sizes = [len(f) for f in facets]
    # each (merged vertex, plane) incidence once
    pairs = np.unique(np.stack([np.repeat(group, sizes), np.concatenate(facets).astype(np.int64)], axis=1), axis=0)
    vertex_of, plane_of = pairs[:, 0], pairs[:, 1]
    tri, tri_plane = _face_fans(verts, vertex_of, plane_of, hs[:, :3], with_planes=True)  # (F, 3, 3), (F,)
    centre = verts.mean(0)
    c = np.broadcast_to(centre, tri[:, 0].shape)
    # Extended precision (x87 long double on x86): a needle cell (1e-5 wide,
    # 0.1 long) fans into slivers whose determinants cancel; in float64 its
    # second moment came out 1.2e-10 off the exact rational value.
    vol, first_moment, second = tetrahedron_integrals(c, tri[:, 0], tri[:, 1], tri[:, 2], np.longdouble)
    volume = float(vol.sum())
    with np.errstate(divide="ignore", invalid="ignore"):  # a cell Qhull lost: no volume, NaN centroid
        centroid = (first_moment.sum(0) / vol.sum()).astype(np.float64)
    # a plane bounds a facet when at least 3 distinct vertices lie on it
    planes, count = np.unique(plane_of, return_counts=True)
    facets = sorted(int(owner[h]) for h, cnt in zip(planes, count) if cnt >= 3 and owner[h] >= 0)
    tri_area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    area = float(tri_area.sum())
    # each face: its area and centroid, by its point (>= 0) or wall (-1 - w: -x, +x, -y, +y, -z, +z)
    faces = {}
    wall_of_plane = [-1, -3, -5, -2, -4, -6]  # box_hs: the lo walls of x, y, z, then the hi walls
    for h in np.unique(tri_plane):
        on = tri_plane == h
        a = float(tri_area[on].sum())
        if a > 0:
            key = int(owner[h]) if owner[h] >= 0 else wall_of_plane[int(h)]
            faces[key] = (a, (tri_area[on, None] * tri[on].mean(1)).sum(0) / a + seed)
    return CellOracle(volume, centroid + seed, float(second.sum()), verts + seed,
                      np.array(facets, dtype=np.int64), seed, area=area, faces=faces,
                      relative_radius=float(np.sqrt((verts ** 2).sum(1).max())) if len(verts) else 0.0)


def voronoi_oracle(points, box, cells: Optional[Sequence[int]] = None):
    """Oracle for many cells: (volume (C,), centroid (C, 3), second_moment (C,),
    duplicate (C,) bool) for the cell indices `cells` (default: all)."""
    pts = _np64(points)
    if cells is None:
        cells = range(len(pts))
    out = [voronoi_cell_oracle(pts, int(i), box) for i in cells]
    return (np.array([c.volume for c in out]), np.array([c.centroid for c in out]).reshape(-1, 3),
            np.array([c.second_moment for c in out]), np.array([c.duplicate for c in out], dtype=bool))


# ----------------------------------------------------------------------------- exact cells


def _cross(a, b):
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _solve3(planes):
    """The point where three planes (n, c) with n . x = c meet, exactly, or None."""
    (n0, c0), (n1, c1), (n2, c2) = planes
    n12, n20, n01 = _cross(n1, n2), _cross(n2, n0), _cross(n0, n1)
    det = _dot(n0, n12)
    if det == 0:
        return None
    return tuple((c0 * n12[a] + c1 * n20[a] + c2 * n01[a]) / det for a in range(3))


def _ring_order(ring, normal):
    """The exact points `ring` of a convex polygon in the plane with `normal`,
    in order around it: an angular sort about their mean by half-plane, then
    by the sign of a cross product (no angle is computed)."""
    from fractions import Fraction
    from functools import cmp_to_key

    axis = min(range(3), key=lambda a: abs(normal[a]))
    u = _cross(normal, tuple(Fraction(int(a == axis)) for a in range(3)))
    w = _cross(normal, u)
    centre = tuple(sum(v[a] for v in ring) / len(ring) for a in range(3))
    coords = {}
    for v in ring:
        offset = tuple(v[a] - centre[a] for a in range(3))
        coords[v] = (_dot(offset, u), _dot(offset, w))

    def half(c):  # 0 for angles in [0, pi), 1 for [pi, 2 pi)
        return 0 if (c[1] > 0 or (c[1] == 0 and c[0] > 0)) else 1

    def compare(p, q):
        cp, cq = coords[p], coords[q]
        if half(cp) != half(cq):
            return half(cp) - half(cq)
        cross = cp[0] * cq[1] - cp[1] * cq[0]
        return -1 if cross > 0 else (1 if cross < 0 else 0)

    return sorted(ring, key=cmp_to_key(compare))


class _ExactCell:
    """A convex polytope in exact arithmetic, clipped one plane at a time:
    vertex k is `coords[k]` (exact), `through[k]` the indices of the planes
    through it; `approx` (in the order of `order`) their float64 rounding,
    which screens the exact tests (a vertex clearly inside a plane is not
    tested exactly). Starts as the box (planes 0-5: for each axis its hi
    wall, then its lo wall)."""

    def __init__(self, planes):
        self.planes = planes
        self.coords, self.through, self.count = {}, {}, 0
        for pick in np.ndindex(2, 2, 2):
            triple = [2 * a + int(pick[a]) for a in range(3)]
            self._add(_solve3([planes[t] for t in triple]), set(triple))
        self._floats()

    def _add(self, v, through) -> None:
        self.coords[self.count], self.through[self.count] = v, through
        self.count += 1

    def _floats(self) -> None:
        self.order = list(self.coords)
        self.approx = np.array([[float(x) for x in self.coords[k]] for k in self.order]).reshape(-1, 3)

    def vertices(self):
        """{exact vertex: indices of the planes through it}."""
        return {self.coords[k]: self.through[k] for k in self.order}

    def clip(self, index: int) -> None:
        """Keep n . x <= c of planes[index] = (n, c); the index joins the sets
        of the vertices on it. Two vertices end one edge when two non-parallel
        planes pass through both (a line meets a convex polytope in one
        segment, whose ends are its only vertices on the line); where the plane
        crosses an edge, the new vertex is solved from those two and it."""
        n, c = self.planes[index]
        nf, cf = np.array([float(x) for x in n]), float(c)
        screen = self.approx @ nf - cf
        slack = 1e-9 * (np.abs(self.approx).sum(axis=1) * np.abs(nf).max() + abs(cf))  # far above its rounding
        side = {self.order[r]: _dot(n, self.coords[self.order[r]]) - c for r in np.flatnonzero(screen > -slack)}
        for k in (k for k, s in side.items() if s == 0):
            self.through[k].add(index)
        beyond = [k for k, s in side.items() if s > 0]
        if not beyond:
            return
        inside = [k for k in self.order if side.get(k, -1) < 0]
        added = []
        for w in beyond:
            for u in inside:
                common = self.through[u] & self.through[w]
                pair = next(((a, b) for a, b in itertools.combinations(sorted(common), 2)
                             if _cross(self.planes[a][0], self.planes[b][0]) != (0, 0, 0)), None)
                if pair is not None:
                    added.append((_solve3([self.planes[pair[0]], self.planes[pair[1]], self.planes[index]]),
                                  common | {index}))
        for w in beyond:
            del self.coords[w], self.through[w]
        for v, through in added:
            self._add(v, through)
        self._floats()


def _violated(cell, rel_float, offset_float, rel, offset, chosen):
    """The points whose bisector (rel[j] . x <= offset(j)) some vertex of the
    _ExactCell lies beyond, exactly; a float64 screen (rel_float,
    offset_float: the same planes rounded) spares the exact test of a vertex
    clearly inside a point's plane (by far more than the screen's rounding,
    which scales with that point's own distance and offset)."""
    vertices, corners = [cell.coords[k] for k in cell.order], cell.approx
    radius = float(np.abs(corners).sum(axis=1).max())
    slack = 1e-9 * (radius * np.abs(rel_float).sum(axis=1) + np.abs(offset_float))
    violated = []
    for begin in range(0, len(rel_float), 4096):  # bounded memory: vertices x a chunk of points
        screen = corners @ rel_float[begin:begin + 4096].T - offset_float[begin:begin + 4096]
        for column in np.flatnonzero((screen > -slack[begin:begin + 4096]).any(axis=0)):
            j = begin + int(column)
            if j in chosen or rel[j] == (0, 0, 0):
                continue
            rows = np.flatnonzero(screen[:, column] > -slack[j])
            if any(_dot(rel[j], vertices[r]) > offset(j) for r in rows[np.argsort(-screen[rows, column])]):
                violated.append(j)
    return violated


def exact_cell_oracle(points, i: int, box, candidates: Optional[Sequence[int]] = None, weights=None) -> CellOracle:
    """Voronoi cell of points[i] clipped to box = (lo, hi), its vertices in exact
    rational arithmetic (Fractions over the float64 inputs), its integrals
    exact per tetrahedron and summed in float64: for cells whose vertices
    nearly coincide (bisectors of tight clusters), where Qhull's vertices and
    their merging are off by more than float64 rounding.

    The box is clipped by the half-spaces of `candidates` (point indices;
    default: Qhull's facet neighbours, voronoi_cell_oracle) one at a time
    (_ExactCell.clip); then each vertex is checked against the bisectors of all
    points, and the violated ones clip it too, until none is (then the cell is
    exact: it lies inside every half-space, and every one cut it). Integrals
    over the fans of the faces from the seed (as tetrahedron_integrals).
    Slow (its time grows with the facets): for single cells. Exact copies
    among the candidates give one plane, and copies of the seed none; a seed
    with a lower-index copy (a DUPLICATE cell) is not handled here (use
    voronoi_cell_oracle). With `weights` (N,), the power cell (power
    bisectors; not an empty one: use voronoi_cell_oracle), its fans taken
    from a vertex (the seed can lie outside it).
    """
    from fractions import Fraction

    pts = _np64(points)
    lo, hi = (_np64(b).reshape(3) for b in box)
    if candidates is None:
        candidates = voronoi_cell_oracle(pts, i, (lo, hi), weights=weights).facet_neighbors.tolist()
    exact = [tuple(Fraction(float(c)) for c in p) for p in pts]
    seed = exact[i]
    rel = [tuple(q[a] - seed[a] for a in range(3)) for q in exact]
    w = [Fraction(0)] * len(pts) if weights is None else [Fraction(float(x)) for x in _np64(weights).reshape(-1)]

    def offset(j):  # x . r <= (|r|^2 + w_i - w_j) / 2, relative to the seed
        return (_dot(rel[j], rel[j]) + w[i] - w[j]) / 2

    def bisector(j):
        return (rel[j], offset(j))

    box_planes = []
    for a in range(3):
        unit = tuple(Fraction(int(a == b)) for b in range(3))
        box_planes.append((unit, Fraction(float(hi[a])) - seed[a]))            # x_a <= hi_a
        box_planes.append((tuple(-u for u in unit), seed[a] - Fraction(float(lo[a]))))  # -x_a <= -lo_a
    # One plane a distinct offset: a face counted once however many copies bound it.
    chosen, offsets = [], set()
    for j in sorted(set(int(j) for j in candidates) - {i}):
        if rel[j] != (0, 0, 0) and rel[j] not in offsets:
            offsets.add(rel[j])
            chosen.append(j)
    rel_float = pts - pts[i]
    offset_float = 0.5 * (rel_float ** 2).sum(axis=1)
    if weights is not None:
        offset_float += 0.5 * (float(w[i]) - _np64(weights).reshape(-1))
    planes = box_planes + [bisector(j) for j in chosen]
    cell = _ExactCell(planes)
    for t in sorted(range(6, len(planes)), key=lambda t: planes[t][1] * abs(planes[t][1]) / _dot(*[planes[t][0]] * 2)):
        cell.clip(t)  # nearest bisectors first: the cell shrinks early
    while True:  # every vertex inside every point's bisector, or the violated ones clip it too
        violated = _violated(cell, rel_float, offset_float, rel, offset, set(chosen) | {i})
        if not violated:
            break
        for j in violated:
            chosen.append(j)
            planes.append(bisector(j))
            cell.clip(len(planes) - 1)
    vertices = cell.vertices()
    # Each face: its vertices in order around it (_ring_order), fanned from
    # the first; tetrahedra with apex o in the closed convex cell: the seed (short
    # numbers), or for a power cell (whose seed can lie outside it) its least vertex.
    if not vertices:
        raise RuntimeError("exact oracle: empty cell")
    o = (Fraction(0),) * 3 if weights is None else min(vertices)
    on_plane = {}
    for v, through in vertices.items():
        for t in through:
            on_plane.setdefault(t, []).append(v)
    # Each tetrahedron's integrals exact, then rounded and summed by fsum: exact sums of
    # many vertices' denominators grow too long; the volumes and second moments are sums of
    # positive terms (relative error 1e-16), the first moments within 1e-16 of the radius.
    volumes, firsts, seconds = [], [], []
    area2_total = 0.0
    faces = {}  # as voronoi_cell_oracle's: by point (>= 0) or wall (-1 - w)
    seen = set()  # a face on two coincident planes (a bisector on a box wall) counted once
    for t, ring in on_plane.items():
        if len(ring) < 3 or frozenset(ring) in seen:
            continue
        seen.add(frozenset(ring))
        ordered = _ring_order(ring, planes[t][0])
        a0 = ordered[0]
        face_area2, face_moment = 0.0, np.zeros(3)
        for b, c in zip(ordered[1:-1], ordered[2:]):
            six = _dot(tuple(a0[a] - o[a] for a in range(3)),
                       _cross(tuple(b[a] - o[a] for a in range(3)), tuple(c[a] - o[a] for a in range(3))))
            vol = abs(six) / 6
            volumes.append(float(vol))
            total = tuple(o[a] + a0[a] + b[a] + c[a] for a in range(3))
            firsts.append([float(vol * total[a] / 4) for a in range(3)])
            seconds.append(float(vol / 20 * (_dot(o, o) + _dot(a0, a0) + _dot(b, b) + _dot(c, c) + _dot(total, total))))
            e1 = np.array([float(b[a] - a0[a]) for a in range(3)])
            e2 = np.array([float(c[a] - a0[a]) for a in range(3)])
            area2 = float(np.linalg.norm(np.cross(e1, e2)))
            area2_total += area2
            face_area2 += area2
            face_moment += area2 * np.array([float(a0[a] + b[a] + c[a]) for a in range(3)]) / 3
        if face_area2 > 0:
            # box_planes: for each axis a, the hi wall (2a + 1), then the lo wall (2a)
            key = chosen[t - 6] if t >= 6 else -1 - (2 * (t // 2) + (1 - t % 2))
            faces[key] = (0.5 * face_area2, face_moment / face_area2 + pts[i])
    seed_np = pts[i]
    relative = np.array([[float(x) for x in v] for v in vertices])
    verts = relative + seed_np
    radius = max((math.sqrt(float(_dot(v, v))) for v in vertices), default=0.0)  # exact |v|^2, one rounding
    volume, second = math.fsum(volumes), math.fsum(seconds)
    centroid = np.array([math.fsum(f[a] for f in firsts) / volume for a in range(3)]) + seed_np
    facets = sorted(chosen[t - 6] for t, ring in on_plane.items() if len(ring) >= 3 and t >= 6)
    return CellOracle(volume, centroid, second, verts, np.array(facets, dtype=np.int64),
                      seed_np.copy(), area=0.5 * area2_total, faces=faces, relative_radius=radius)


# ----------------------------------------------------------------------------- periodic boxes

def periodic_cell_oracle(points, i: int, box, periodic, weights=None) -> CellOracle:
    """The Voronoi cell of points[i] (points inside box) when the box repeats
    along the axes `periodic` (3 bools): voronoi_cell_oracle over the points
    and their images shifted by every s in {-t..t}^3 on those axes, in a box
    wide enough not to cut it; t grows until twice the cell's radius is
    within t periods. Faces are keyed by (point, shift) (walls: (-1 - w, None)).
    With `weights` (N,), the power cell, images carrying their point's weight:
    t grows until ``R + sqrt(R^2 + max w - w_i)`` is within t periods (an
    empty cell is empty from t = 1 on: its own images keep the true cell
    within half a period of the point, inside the wide box)."""
    pts = _np64(points)
    w = None if weights is None else _np64(weights).reshape(-1)
    lo, hi = (_np64(b).reshape(3) for b in box)
    axes = np.array(periodic, dtype=bool)
    period = np.where(axes, hi - lo, 0.0)
    n = len(pts)
    for turns in range(1, 6):
        ranges = [range(-turns, turns + 1) if a else range(1) for a in axes]
        shifts = np.array([s for s in itertools.product(*ranges) if any(s)], dtype=np.int64).reshape(-1, 3)
        images = (pts[None, :, :] + shifts[:, None, :] * period).reshape(-1, 3)
        every = np.concatenate([pts, images])
        shift_of = np.concatenate([np.zeros((n, 3), np.int64), np.repeat(shifts, n, axis=0)])
        wide = (lo - turns * period, hi + turns * period)
        every_w = None if w is None else np.tile(w, len(shifts) + 1)
        cell = voronoi_cell_oracle(every, i, wide, weights=every_w)
        if w is None:
            reach = 2 * cell.radius
        else:
            reach = 0.0 if cell.empty else cell.radius + np.sqrt(cell.radius ** 2 + w.max() - w[i])
        if cell.duplicate or not axes.any() or reach <= turns * period[axes].min():
            break
    if cell.faces is not None:
        faces = {}
        for key, value in cell.faces.items():
            if key >= 0:
                faces[(key % n, tuple(int(v) for v in shift_of[key]))] = value
            else:
                faces[(key, None)] = value
        cell.faces = faces
    return cell


def minimum_image_dist2(queries, points, box, periodic) -> np.ndarray:
    """(M, N) float64 squared distances at the nearest image along the periodic axes."""
    q, p = _np64(queries), _np64(points)
    lo, hi = (_np64(b).reshape(3) for b in box)
    period = np.where(np.array(periodic, dtype=bool), hi - lo, 0.0)
    d = p[None, :, :] - q[:, None, :]
    safe = np.where(period > 0, period, 1.0)
    d = d - np.where(period > 0, np.round(d / safe), 0.0) * period
    return (d * d).sum(-1)
