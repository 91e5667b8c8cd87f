"""Point sets for the fuzzing campaign (tests/fuzz.py): the kinds of input, each case
drawn from a numpy Generator seeded by (campaign seed, case index) alone."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Dict, Optional, Sequence

import numpy as np
import torch

DTYPES = {"float32": torch.float32, "float64": torch.float64}
DTYPE_NAMES = {v: k for k, v in DTYPES.items()}
INVALID_EVERY = 41  # case I is an invalid input when I % INVALID_EVERY == INVALID_EVERY - 1 (41: every kind in turn)


@dataclass
class Cloud:
    """One point cloud before rounding: absolute float64 coordinates, its
    nominal box, and how the box is passed: "given" (the nominal box),
    "bbox" (box=None: the points' bounding box) or "enclose" (an explicit
    box around the points, with a random margin)."""

    points: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    mode: str = "given"


@dataclass
class Case:
    """One fuzz input, exactly as torchvor sees it: `points` are float64
    values representable in `dtype`, `boxes` (B, 2, 3) likewise (the boxes
    the diagram is clipped to, also for box=None), `box_arg` how the box is
    passed ("none", "pair" or "tensor"). `expect_error` is a regex that the
    ValueError of an invalid input must match (None: a valid input)."""

    seed: int
    index: int
    kind: str
    dtype: torch.dtype
    points: np.ndarray
    batch: Optional[np.ndarray]
    boxes: np.ndarray
    box_arg: str
    params: Dict = field(default_factory=dict)
    expect_error: Optional[str] = None

    @property
    def n(self) -> int:
        return int(self.points.shape[0])

    def clouds(self):
        """(cloud id, global indices, (lo, hi)) of every non-empty cloud."""
        if self.batch is None:
            yield 0, np.arange(self.n), (self.boxes[0, 0], self.boxes[0, 1])
            return
        for k in np.unique(self.batch):
            box = self.boxes[0] if len(self.boxes) == 1 else self.boxes[k]
            yield int(k), np.nonzero(self.batch == k)[0], (box[0], box[1])

    def arguments(self, device):
        """(points, box, batch) for torchvor.voronoi on `device`."""
        points = torch.tensor(self.points, dtype=self.dtype).to(device)
        batch = None if self.batch is None else torch.tensor(self.batch, dtype=torch.int64).to(device)
        if self.box_arg == "none":
            box = None
        elif self.box_arg == "pair":
            box = (self.boxes[0, 0].tolist(), self.boxes[0, 1].tolist())
        else:
            box = torch.tensor(self.boxes, dtype=self.dtype).to(device)
        return points, box, batch

    def describe(self) -> str:
        """One line: index, kind, dtype, size, clouds, how the box is passed, the drawn parameters."""
        clouds = "" if self.batch is None else f", {len(np.unique(self.batch))} clouds"
        params = ", ".join(f"{k}={_short(v)}" for k, v in self.params.items())
        invalid = f", invalid: {self.expect_error!r}" if self.expect_error else ""
        return (f"case {self.index} {self.kind} {DTYPE_NAMES[self.dtype]} n={self.n}{clouds}, "
                f"box={self.box_arg} ({params}){invalid}")


def _short(v):
    """A parameter value, short."""
    if isinstance(v, float):
        return f"{v:.3g}"
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(str(_short(x)) for x in v) + "]"
    return v


def _log_uniform(rng, a: float, b: float) -> float:
    """Log-uniform in [a, b]."""
    return float(math.exp(rng.uniform(math.log(a), math.log(b))))


def _size(rng, max_n: int) -> int:
    """Log-uniform in 1..max_n."""
    return int(min(max_n, max(1, math.floor(math.exp(rng.uniform(0.0, math.log(max_n + 1)))))))


def _to_box(u: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Unit-cube coordinates mapped onto [lo, hi]; 0 and 1 land exactly on the walls."""
    x = lo + u * (hi - lo)
    x = np.where(u == 0.0, lo, x)
    return np.where(u == 1.0, hi, x)


def _unit_box():
    """[0, 1]^3."""
    return np.zeros(3), np.ones(3)


def _aniso_box(rng):
    """Extents log-uniform in 1e-3..1e3 per axis; offsets 0 or up to 1e4 in size."""
    extent = np.array([_log_uniform(rng, 1e-3, 1e3) for _ in range(3)])
    if rng.random() < 0.3:
        offset = np.zeros(3)
    else:
        offset = np.array([rng.choice([-1.0, 1.0]) * _log_uniform(rng, 1e-2, 1e4) for _ in range(3)])
    return offset, offset + extent


def _slab_box(rng):
    """1 x 1 x h with h log-uniform in 1e-7..1e-3, along a random axis, maybe offset."""
    extent = np.ones(3)
    extent[rng.integers(3)] = _log_uniform(rng, 1e-7, 1e-3)
    offset = np.zeros(3) if rng.random() < 0.6 else rng.uniform(-100, 100, 3)
    return offset, offset + extent


# point generators in the unit cube (u coordinates); each returns (u, params)

def _u_uniform(rng, n):
    """White noise in the cube."""
    return rng.random((n, 3)), {}


def _u_clusters(rng, n, clamp=True):
    """Gaussian clusters, spread log-uniform in 1e-6..1e-1, clamped into the cube or not."""
    spread = _log_uniform(rng, 1e-6, 1e-1)
    count = int(min(n, max(1, round(_log_uniform(rng, 1, 50)))))
    centres = rng.uniform(0.1, 0.9, (count, 3))
    u = centres[rng.integers(0, count, n)] + spread * rng.standard_normal((n, 3))
    return (np.clip(u, 0.0, 1.0) if clamp else u), {"spread": spread, "clusters": count, "clamped": clamp}


def _u_walls_clamped(rng, n):
    """Uniform in [-a, 1 + a]^3 clamped into the cube: points on faces, edges, corners."""
    a = _log_uniform(rng, 0.01, 1.0)
    return np.clip(rng.uniform(-a, 1 + a, (n, 3)), 0.0, 1.0), {"overshoot": a}


def _u_walls_quantised(rng, n):
    """Coordinates snapped onto the walls (each with probability p), or
    quantised onto a coarse grid that includes the walls."""
    u = rng.random((n, 3))
    if rng.random() < 0.5:
        p = rng.uniform(0.05, 0.9)
        mask = rng.random((n, 3)) < p
        u[mask] = rng.integers(0, 2, int(mask.sum())).astype(np.float64)
        return u, {"snap": p}
    q = int(rng.choice([1, 2, 3, 4, 5, 8, 10, 16, 32, 64]))
    return np.round(u * q) / q, {"grid": q}


def _u_wall_layer(rng, n):
    """A dense layer on one wall (thickness 0 or log-uniform 1e-6..1e-2) and
    a few sparse points above it: their cells have hundreds of faces."""
    axis, top = int(rng.integers(3)), bool(rng.integers(2))
    sparse = int(min(n - 1, rng.integers(1, 21))) if n > 1 else 0
    dense = n - sparse
    thick = 0.0 if rng.random() < 0.25 else _log_uniform(rng, 1e-6, 1e-2)
    u = rng.random((n, 3))
    u[:dense, axis] *= thick
    u[dense:, axis] = thick + (1 - thick) * u[dense:, axis] ** rng.uniform(0.3, 1.0)
    if top:
        u[:, axis] = 1.0 - u[:, axis]
    return u, {"axis": axis, "thickness": thick, "sparse": sparse}


def _lattice_axes(rng, n):
    """Lattice sizes per axis, about n^(1/3) each (equal, or each within a
    factor 2; powers of two half the time), at most n points in all."""
    m = max(1, int(round(n ** (1 / 3))))
    ms = [m] * 3 if rng.random() < 0.5 else [max(1, int(round(m * 2 ** rng.uniform(-1, 1)))) for _ in range(3)]
    if rng.random() < 0.5:  # powers of two: exactly representable, exactly cospherical
        ms = [1 << max(0, int(round(math.log2(k)))) for k in ms]
    while np.prod(ms) > max(n, 1):
        ms[int(np.argmax(ms))] -= 1
    ms = [max(1, k) for k in ms]
    return ms


def _u_lattice(rng, n):
    """An exact lattice: cell centres (i + 0.5) / m, or nodes i / (m - 1) (on the walls)."""
    ms = _lattice_axes(rng, n)
    nodes = rng.random() < 0.5
    axes = [((np.arange(k) / (k - 1)) if (nodes and k > 1) else (np.arange(k) + 0.5) / k) for k in ms]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    u = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    return u, {"lattice": ms, "nodes": nodes}


def _u_lattice_jittered(rng, n):
    """Lattice centres moved uniformly by up to amp (log-uniform 1e-12..0.45) spacings."""
    ms = _lattice_axes(rng, n)
    axes = [(np.arange(k) + 0.5) / k for k in ms]
    z, y, x = np.meshgrid(axes[2], axes[1], axes[0], indexing="ij")
    u = np.stack([x.ravel(), y.ravel(), z.ravel()], 1)
    amp = _log_uniform(rng, 1e-12, 0.45)
    u = u + rng.uniform(-amp, amp, u.shape) / np.array(ms)
    return np.clip(u, 0.0, 1.0), {"lattice": ms, "jitter": amp}


def _u_gradient(rng, n):
    """Density growing towards a wall (u = r^p along an axis, p up to 20) or a
    point (radius r^p about it)."""
    p = _log_uniform(rng, 1.0, 20.0)
    u = rng.random((n, 3))
    if rng.random() < 0.5:
        axis = int(rng.integers(3))
        u[:, axis] = u[:, axis] ** p
        return u, {"power": p, "axis": axis}
    centre = rng.random(3)
    direction = rng.standard_normal((n, 3))
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
    u = centre + 0.7 * (rng.random((n, 1)) ** p) * direction
    return np.clip(u, 0.0, 1.0), {"power": p, "centre": centre.tolist()}


def _u_duplicates(rng, n):
    """n draws with replacement from m < n base points (uniform, lattice or
    on the walls): exact copies, in random order."""
    m = max(1, int(round(n * rng.uniform(0.05, 0.9))))
    base_kind = rng.choice(["uniform", "lattice", "walls"])
    base = {"uniform": _u_uniform, "lattice": _u_lattice, "walls": _u_walls_quantised}[base_kind](rng, m)[0]
    return base[rng.integers(0, len(base), n)], {"base": str(base_kind), "base_points": len(base)}


INNER = {
    "uniform": _u_uniform,
    "clusters": _u_clusters,
    "walls_clamped": _u_walls_clamped,
    "walls_quantised": _u_walls_quantised,
    "wall_layer": _u_wall_layer,
    "lattice": _u_lattice,
    "lattice_jittered": _u_lattice_jittered,
    "gradient": _u_gradient,
    "duplicates": _u_duplicates,
}


def _inner(rng, n, choices):
    """Points of a unit-cube generator drawn among `choices`."""
    name = str(rng.choice(choices))
    u, params = INNER[name](rng, n)
    return u, dict(params, inner=name)


def _close_pairs(rng, n, lo, hi, dtype):
    """n / 2 uniform points and, next to each, a partner 1e-7 (times up to 10
    either way) of the box size away (float64), or 1-4 ulps of the dtype away
    on 1-3 coordinates (float32, and a fifth of the float64 cases)."""
    m = max(1, n // 2)
    base = _round(_to_box(rng.random((m, 3)), lo, hi), dtype)
    if dtype == torch.float64 and rng.random() < 0.8:
        d = 1e-7 * 10 ** rng.uniform(-1, 1)
        direction = rng.standard_normal((m, 3))
        direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-300)
        partner = base + d * (hi - lo) * direction
        params = {"distance": d}
    else:
        np_dtype = np.float32 if dtype == torch.float32 else np.float64
        partner = base.astype(np_dtype)
        steps = rng.integers(1, 5, (m, 3)) * (rng.random((m, 3)) < 0.6)
        steps[np.arange(m), rng.integers(0, 3, m)] = rng.integers(1, 5, m)  # at least one coordinate moves
        sign = np.where(rng.random((m, 3)) < 0.5, -np.inf, np.inf).astype(np_dtype)
        for _ in range(int(steps.max())):
            move = steps > 0
            partner = np.where(move, np.nextafter(partner, sign), partner)
            steps = steps - 1
        partner = partner.astype(np.float64)
        params = {"ulps": "1-4"}
    points = np.concatenate([base, partner])[:max(n, 1)]
    return np.clip(points, lo, hi), params


# kinds: each returns (clouds, box policy, params). The box policy of a batch
# is "shared" (one box for all clouds) or "per_cloud".

def kind_clusters(rng, n, dtype):
    """Gaussian clusters in the unit cube: clamped into it (the box given, or the bounding box), or
    not (the bounding box, or a box around them)."""
    clamp = rng.random() < 0.5
    u, params = _u_clusters(rng, n, clamp)
    lo, hi = _unit_box()
    mode = ("given" if rng.random() < 0.8 else "bbox") if clamp else str(rng.choice(["bbox", "enclose"]))
    return [Cloud(u, lo, hi, mode)], None, params


def kind_walls_clamped(rng, n, dtype):
    """Points clamped onto the walls, edges and corners of the unit cube or an anisotropic box."""
    u, params = _u_walls_clamped(rng, n)
    lo, hi = _unit_box() if rng.random() < 0.7 else _aniso_box(rng)
    return [Cloud(_to_box(u, lo, hi), lo, hi)], None, params


def kind_walls_quantised(rng, n, dtype):
    """Points snapped onto the walls, or onto a coarse grid through them, of the unit cube or an
    anisotropic box."""
    u, params = _u_walls_quantised(rng, n)
    lo, hi = _unit_box() if rng.random() < 0.7 else _aniso_box(rng)
    return [Cloud(_to_box(u, lo, hi), lo, hi)], None, params


def kind_wall_layer(rng, n, dtype):
    """A dense layer on a wall of the unit cube and a few points above it."""
    u, params = _u_wall_layer(rng, n)
    lo, hi = _unit_box()
    return [Cloud(u, lo, hi)], None, params


def kind_thin_slab(rng, n, dtype):
    """Points in a 1 x 1 x h slab, h down to 1e-7."""
    lo, hi = _slab_box(rng)
    u, params = _inner(rng, n, ["uniform", "uniform", "clusters", "lattice_jittered", "walls_clamped"])
    mode = "given" if rng.random() < 0.8 else "bbox"
    return [Cloud(_to_box(u, lo, hi), lo, hi, mode)], None, dict(params, thickness=float((hi - lo).min()))


def kind_lattice(rng, n, dtype):
    """An exact lattice in the unit cube or an anisotropic box (nodes with box=None at times)."""
    u, params = _u_lattice(rng, n)
    lo, hi = _unit_box() if rng.random() < 0.8 else _aniso_box(rng)
    mode = "bbox" if params["nodes"] and rng.random() < 0.3 else "given"
    return [Cloud(_to_box(u, lo, hi), lo, hi, mode)], None, params


def kind_lattice_jittered(rng, n, dtype):
    """A lattice jittered by 1e-12 .. 0.45 spacings."""
    u, params = _u_lattice_jittered(rng, n)
    lo, hi = _unit_box()
    return [Cloud(u, lo, hi)], None, params


def kind_close_pairs(rng, n, dtype):
    """Pairs of points 1e-7 of the box apart, or a few ulps."""
    lo, hi = _unit_box() if rng.random() < 0.7 else _aniso_box(rng)
    points, params = _close_pairs(rng, n, lo, hi, dtype)
    return [Cloud(points, lo, hi)], None, params


def kind_duplicates(rng, n, dtype):
    """Exact copies of fewer base points."""
    u, params = _u_duplicates(rng, n)
    lo, hi = _unit_box()
    return [Cloud(u, lo, hi)], None, params


def kind_aniso_box(rng, n, dtype):
    """Points of several kinds in a box of extents 1e-3..1e3, offsets up to 1e4."""
    lo, hi = _aniso_box(rng)
    u, params = _inner(rng, n, ["uniform", "clusters", "walls_clamped", "lattice", "gradient"])
    mode = "given" if rng.random() < 0.8 else "bbox"
    return [Cloud(_to_box(u, lo, hi), lo, hi, mode)], None, dict(params, lo=lo.tolist(), hi=hi.tolist())


def kind_gradient(rng, n, dtype):
    """A density gradient towards a wall or a point."""
    u, params = _u_gradient(rng, n)
    lo, hi = _unit_box()
    return [Cloud(u, lo, hi)], None, params


def kind_tiny(rng, n, dtype):
    """1-10 points in an explicit box: uniform, some snapped to walls or copied."""
    n = int(rng.integers(1, 11))
    lo, hi = _unit_box() if rng.random() < 0.5 else _aniso_box(rng)
    u = rng.random((n, 3))
    snap = rng.random((n, 3)) < 0.2
    u[snap] = rng.integers(0, 2, int(snap.sum())).astype(np.float64)
    copies = rng.random(n) < 0.15
    copies[0] = False
    u[copies] = u[rng.integers(0, n, int(copies.sum()))]
    return [Cloud(_to_box(u, lo, hi), lo, hi)], None, {"lo": lo.tolist(), "hi": hi.tolist()}


def kind_white_noise(rng, n, dtype):
    """White noise in the unit cube: box given, the bounding box, or a box around it (cells reaching
    to far walls)."""
    lo, hi = _unit_box()
    u = rng.random((n, 3))
    mode = str(rng.choice(["given", "given", "bbox", "enclose"]))
    return [Cloud(u, lo, hi, mode)], None, {}


def _batch_clouds(rng, n, boxes):
    """Clouds of random inner kinds, sizes a random split of n, one per box."""
    weights = rng.dirichlet(np.full(len(boxes), 0.7))
    clouds, inner = [], []
    for (lo, hi), w in zip(boxes, weights):
        size = max(1, int(round(n * w)))
        u, params = _inner(rng, size, list(INNER))
        clouds.append(Cloud(_to_box(u, lo, hi), lo, hi))
        inner.append(params["inner"])
    return clouds, inner


def kind_batch_shared_box(rng, n, dtype):
    count = int(rng.integers(2, 7))
    box = _unit_box() if rng.random() < 0.6 else _aniso_box(rng)
    clouds, inner = _batch_clouds(rng, n, [box] * count)
    return clouds, "shared", {"inner": inner}


def kind_batch_per_cloud_box(rng, n, dtype):
    count = int(rng.integers(2, 7))
    boxes = [_unit_box() if rng.random() < 0.3 else _aniso_box(rng) for _ in range(count)]
    clouds, inner = _batch_clouds(rng, n, boxes)
    if rng.random() < 0.25:
        for c in clouds:
            c.mode = "bbox"
    return clouds, "per_cloud", {"inner": inner}


KINDS: Dict[str, Callable] = {
    "clusters": kind_clusters,
    "walls_clamped": kind_walls_clamped,
    "walls_quantised": kind_walls_quantised,
    "wall_layer": kind_wall_layer,
    "thin_slab": kind_thin_slab,
    "lattice": kind_lattice,
    "lattice_jittered": kind_lattice_jittered,
    "close_pairs": kind_close_pairs,
    "duplicates": kind_duplicates,
    "aniso_box": kind_aniso_box,
    "gradient": kind_gradient,
    "tiny": kind_tiny,
    "white_noise": kind_white_noise,
    "batch_shared_box": kind_batch_shared_box,
    "batch_per_cloud_box": kind_batch_per_cloud_box,
}


def _np_dtype(dtype):
    return np.float32 if dtype == torch.float32 else np.float64


def _round(x, dtype) -> np.ndarray:
    """x rounded to `dtype`, held in float64."""
    return np.asarray(x, dtype=np.float64).astype(_np_dtype(dtype)).astype(np.float64)


def _round_box(lo, hi, dtype):
    """The box rounded to `dtype`, at least one ulp wide on every axis."""
    lo, hi = _round(lo, dtype), _round(hi, dtype)
    t = _np_dtype(dtype)
    up = np.nextafter(lo.astype(t), t(np.inf)).astype(np.float64)
    return lo, np.where(hi > lo, hi, up)


def _enclosing_box(rng, points, dtype):
    """A box around `points` (already rounded) with a random margin, rounded
    outwards to `dtype`, non-flat."""
    pmin, pmax = points.min(0), points.max(0)
    scale = max(float((pmax - pmin).max()), 1e-3 * max(1.0, float(np.abs(points).max())))
    margin = _log_uniform(rng, 1e-3, 10.0) * scale
    lo = np.minimum(_round(pmin - margin * rng.random(3), dtype), pmin)
    hi = np.maximum(_round(pmax + margin * rng.random(3), dtype), pmax)
    return _round_box(lo, hi, dtype)


def _finish_cloud(rng, cloud, dtype):
    """(points rounded to dtype and inside the box, (lo, hi), whether the box
    is the bounding box) of one cloud; a flat bounding box falls back to an
    enclosing box."""
    points = _round(cloud.points, dtype)
    if cloud.mode == "given":
        lo, hi = _round_box(cloud.lo, cloud.hi, dtype)
        return np.clip(points, lo, hi), (lo, hi), False
    pmin, pmax = points.min(0), points.max(0)
    if cloud.mode == "bbox" and np.all(pmax > pmin):
        return points, (pmin, pmax), True
    return points, _enclosing_box(rng, points, dtype), False


def _shuffle(rng, points):
    return points[rng.permutation(len(points))] if rng.random() < 0.7 else points


def case_dtype(index: int, dtype: str, kinds: Sequence[str]) -> torch.dtype:
    """float32 or float64; with "both", alternating every round of the kinds."""
    if dtype != "both":
        return DTYPES[dtype]
    return torch.float32 if (index // len(kinds)) % 2 == 0 else torch.float64


def make_case(seed: int, index: int, *, max_n: int = 20000, dtype: str = "both",
              kinds: Optional[Sequence[str]] = None) -> Case:
    """Case `index` of campaign `seed`: its kind by turns, everything else
    drawn from a Generator seeded by (seed, index) alone."""
    kinds = list(kinds or KINDS)
    kind = kinds[index % len(kinds)]
    torch_dtype = case_dtype(index, dtype, kinds)
    rng = np.random.default_rng([seed, index])
    n = _size(rng, max_n)
    clouds, policy, params = KINDS[kind](rng, n, torch_dtype)
    finished = []
    if policy == "shared":
        lo, hi = _round_box(clouds[0].lo, clouds[0].hi, torch_dtype)
        for c in clouds:
            finished.append((np.clip(_round(c.points, torch_dtype), lo, hi), (lo, hi), False))
    else:
        finished = [_finish_cloud(rng, c, torch_dtype) for c in clouds]
    points = np.concatenate([_shuffle(rng, p) for p, _, _ in finished])
    boxes = np.stack([np.stack(b) for _, b, _ in finished])
    all_bbox = all(bbox for _, _, bbox in finished)
    if len(clouds) == 1:
        batch = None
        box_arg = "none" if all_bbox else "pair"
    else:
        ids = np.arange(len(clouds))
        if rng.random() < 0.3:  # an empty cloud between two others
            gap = int(rng.integers(1, len(clouds)))
            ids[gap:] += 1
        batch = np.repeat(ids, [len(p) for p, _, _ in finished])
        spread = np.zeros((ids[-1] + 1, 2, 3))
        spread[:, 1] = 1.0
        spread[ids] = boxes
        boxes = spread
        if policy == "shared":
            box_arg = "pair" if rng.random() < 0.5 else "tensor"
            boxes = boxes[ids[:1]] if box_arg == "pair" else np.repeat(boxes[ids[:1]], len(boxes), 0)
        else:
            box_arg = "none" if all_bbox else "tensor"
        if box_arg == "tensor" and rng.random() < 0.3:  # more boxes than clouds
            boxes = np.concatenate([boxes, boxes[-1:]])
    case = Case(seed, index, kind, torch_dtype, points, batch, boxes, box_arg, params)
    if index % INVALID_EVERY == INVALID_EVERY - 1:
        _make_invalid(rng, case)
    return case


def _make_invalid(rng, case: Case) -> None:
    """Turns `case` into an input torchvor must reject, with the regex its
    ValueError must match: a flat box, coplanar points with box=None, a point
    outside its box, a NaN coordinate, or a box with lo > hi."""
    how = str(rng.choice(["flat_box", "coplanar_bbox", "outside", "nan", "inverted"]))
    members = next(case.clouds())[1]
    axis = int(rng.integers(3))
    case.points = case.points.copy()
    case.boxes = case.boxes.copy()
    first = 0 if (case.batch is None or len(case.boxes) == 1) else int(case.batch[members[0]])
    if case.box_arg == "none" and how in ("flat_box", "outside", "inverted"):
        case.box_arg = "tensor" if case.batch is not None else "pair"
    if how == "coplanar_bbox":
        value = case.points[members[0], axis]
        case.points[members, axis] = value
        case.box_arg = "none"
        case.boxes[first, :, axis] = value
        case.expect_error = r"flat along"
    elif how == "flat_box":
        value = case.boxes[first, 0, axis]
        case.boxes[first, 1, axis] = value
        case.points[members, axis] = value
        case.expect_error = r"flat along"
    elif how == "outside":
        lo, hi = case.boxes[first]
        t = _np_dtype(case.dtype)
        case.points[members[0], axis] = _round(hi[axis] + 0.5 * (hi[axis] - lo[axis]), case.dtype)
        if case.points[members[0], axis] <= hi[axis]:
            case.points[members[0], axis] = float(np.nextafter(t(hi[axis]), t(np.inf)))
        case.expect_error = r"inside box"
    elif how == "nan":
        case.points[members[int(rng.integers(len(members)))], axis] = np.nan
        case.expect_error = r"NaN or Inf"
    else:
        case.boxes[first, :, axis] = case.boxes[first, ::-1, axis].copy()
        case.expect_error = r"lo <= hi"
    case.params = dict(case.params, invalid=how)
