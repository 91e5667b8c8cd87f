"""The fuzzing campaign's checks of periodic boxes (tests/fuzz.py calls
check_periodic on every case small enough): the case's cells with its boxes
periodic along some axes (by turns: all three, x and z, y alone), every cell
computed, each cloud's volumes summing to its box's, and sampled cells
against the half-space oracle over the points' images."""
from __future__ import annotations

import traceback
import warnings
from typing import Dict

import numpy as np
import torch

import torchvor
from torchvor import CellStatus

from oracles import exact_cell_oracle, periodic_cell_oracle

PERIODIC_SAMPLE = 2         # cells of a case whose periodic cell goes to the oracle
PERIODIC_ORACLE_MAX_N = 800  # clouds up to this size (the oracle holds 27 images of each point)
AXES = ((True, True, True), (True, False, True), (False, True, False))


def wrapped(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, axes) -> np.ndarray:
    """The points as torchvor places them in a periodic box (numpy, float64):
    a point inside [lo, hi) unchanged (bit for bit: a cell can hang on the
    last bits of its neighbours), one on hi at lo, any other moved by whole
    periods into [lo, hi) (api.md's rule for points outside the box)."""
    axes = np.asarray(axes)
    period = np.where(axes, hi - lo, 0.0)
    turns = np.where(axes, np.floor((points - lo) / np.where(axes, period, 1.0)), 0.0)
    moved = points - turns * period
    turns = turns + (axes & (moved >= lo + period)) - (axes & (moved < lo))
    moved = points - turns * period
    moved = np.where(axes & ((points == hi) | (moved >= lo + period)), lo, moved)
    inside = (points >= lo) & (points < hi)
    return np.where(~axes | inside, points, moved)


def images_round(lo: np.ndarray, hi: np.ndarray, axes) -> bool:
    """Whether moving a point of [lo, hi) by a period can round in float64
    (exact for a box [0, L] with L a power-of-two multiple of the points'
    spacing; taken as rounding unless lo is 0 along every periodic axis)."""
    return bool(np.any(np.asarray(axes) & (lo != 0)))


def near_pair_across_a_face(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, axes, rounds: float = 1e8) -> bool:
    """Whether two points lie closer than `rounds` roundings of the box's
    coordinates across a periodic face (nearer through an image than
    directly): api.md's limit of periodic cells whose images round."""
    from scipy.spatial import cKDTree

    axes = np.asarray(axes)
    ulp = np.finfo(np.float64).eps * float(np.abs(np.concatenate([lo, hi])).max())
    radius = rounds * ulp
    period = np.where(axes, hi - lo, 0.0)
    inside = points - lo
    if len(points) < 2 or radius <= 0:
        return False
    size = np.where(axes, period, 4 * (np.abs(inside).max() + 1.0))
    tree = cKDTree(np.mod(inside, size), boxsize=size)
    for i, j in tree.query_pairs(radius):
        if np.linalg.norm(points[i] - points[j]) > radius:
            return True  # near only through an image
    return False


def exact_over_images(points: np.ndarray, i: int, lo, hi, axes, candidates: int = 60, weights=None):
    """The exact oracle's volume of cell i among the points and their images
    one period away, from its `candidates` nearest (None where it cannot);
    the power cell with `weights` (N,)."""
    period = np.where(axes, hi - lo, 0.0)
    shifts = [s for s in np.ndindex(*(3 if a else 1 for a in axes)) if any(v != (1 if a else 0) for v, a in
                                                                          zip(s, axes))]
    every = np.concatenate([points] + [points + (np.array(s) - np.array(axes, dtype=np.int64)) * period
                                       for s in shifts])
    distance = ((every - every[i]) ** 2).sum(1)
    nearest = [int(j) for j in np.argsort(distance)[:candidates + 1] if j != i]
    every_w = None if weights is None else np.tile(weights, len(shifts) + 1)
    try:
        return exact_cell_oracle(every, i, (lo - period, hi + period), candidates=nearest, weights=every_w).volume
    except Exception:  # noqa: BLE001 - more facets than the exact oracle takes
        return None


def check_periodic(campaign, case, shared: Dict) -> None:
    from fuzz import CELL_RTOL, SUM_RTOL  # fuzz.py imports this module

    kind, dtype = case.kind, case.dtype
    axes = AXES[case.index % len(AXES)]
    try:
        points, _box, batch = case.arguments(campaign.device)
        boxes = torch.tensor(case.boxes, dtype=dtype).to(campaign.device)
        box = boxes if batch is not None else boxes[0]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cells = torchvor.voronoi(points, box, batch=batch, periodic=axes, on_failure="flag")
    except Exception as error:  # noqa: BLE001 - every exception is a finding
        campaign.report.add(kind, "unexpected_exceptions")
        campaign.problem(case, "periodic", "unexpected_exception",
                         f"periodic {axes}: " + "".join(traceback.format_exception_only(type(error), error)).strip())
        return
    campaign.report.add(kind, "periodic_cells", case.n)
    volume = cells.volume.cpu().double().numpy()
    status = cells.status.cpu().numpy()
    ok = (status == CellStatus.SUCCESS) | (status == CellStatus.DUPLICATE)
    if not ok.all():
        campaign.report.add(kind, "failed_cells", int((~ok).sum()))
        campaign.problem(case, "periodic", "failed", f"periodic {axes}: {int((~ok).sum())} cells failed "
                                                     f"(statuses {sorted(set(status[~ok].tolist()))})")
        return
    rng = np.random.default_rng([case.seed, case.index, 7])
    for cloud, members, (lo, hi) in case.clouds():
        expected = float(np.prod(hi - lo))
        got = volume[members].sum()
        if not abs(got - expected) <= SUM_RTOL[dtype] * expected:
            cloud_points = wrapped(case.points[members].astype(np.float64), lo, hi, axes)
            if images_round(lo, hi, axes) and near_pair_across_a_face(cloud_points, lo, hi, axes):
                campaign.note("periodic volume sum off: a near pair across a face, images rounded (api.md)")
                continue
            campaign.report.add(kind, "wrong_volume_sums")
            campaign.problem(case, "periodic", "volume_sum",
                             f"periodic {axes}, cloud {cloud}: volumes sum to {got!r}, the box's is {expected!r}")
        if len(members) > PERIODIC_ORACLE_MAX_N:
            continue
        cloud_points = wrapped(case.points[members].astype(np.float64), lo, hi, axes)
        for local in rng.choice(len(members), size=min(PERIODIC_SAMPLE, len(members)), replace=False):
            try:
                oracle = periodic_cell_oracle(cloud_points, int(local), (lo, hi), axes)
            except Exception as error:  # noqa: BLE001 - Qhull's limits, not torchvor's
                campaign.report.add(kind, "oracle_skipped")
                campaign.note(f"periodic oracle error: {type(error).__name__}")
                continue
            mine = volume[members[local]]
            if oracle.duplicate:
                good = mine == 0
            else:
                good = abs(mine - oracle.volume) <= CELL_RTOL[dtype] * oracle.volume
                if not good:  # Qhull's own error on slivers: the exact oracle decides
                    exact = exact_over_images(cloud_points, int(local), lo, hi, axes)
                    good = exact is not None and abs(mine - exact) <= CELL_RTOL[dtype] * exact
            if good:
                campaign.report.add(kind, "periodic_certified")
            else:
                campaign.report.add(kind, "silently_wrong")
                campaign.problem(case, "periodic", "periodic",
                                 f"periodic {axes}, cell {int(members[local])}: volume {mine!r}, oracle over the "
                                 f"images {oracle.volume!r} (duplicate {oracle.duplicate})")
