"""The fuzzing campaign's checks of power diagrams (tests/fuzz.py calls
check_power on every case small enough): the case's cells with weights (by
turns: equal, small, about the spacing's square, five times that, each
cloud's own scale), every cell computed (SUCCESS, DUPLICATE or EMPTY), each
cloud's volumes summing to its box's, and sampled cells against the
half-space oracle with power bisectors (empty ones included); then the same
weights with the boxes periodic along some axes (by turns, as
fuzz_periodic.py; cases up to PERIODIC_POWER_MAX_N points), against the
oracle over the images."""
from __future__ import annotations

import traceback
import warnings
from typing import Dict

import numpy as np
import torch

import torchvor
from torchvor import CellStatus

from fuzz_periodic import (AXES, PERIODIC_ORACLE_MAX_N, exact_over_images, images_round, near_pair_across_a_face,
                           wrapped)
from oracles import exact_cell_oracle, periodic_cell_oracle, voronoi_cell_oracle

POWER_SAMPLE = 3            # cells of a case whose power cell goes to the oracle
POWER_ORACLE_MAX_N = 3000   # clouds up to this size (the oracle takes every point's plane)
SPREADS = (0.0, 0.1, 1.0, 5.0)  # weights uniform in [0, spread * s^2], s the cloud's mean spacing
# float32 points' power cells carry float32's guarantee (computed in float32 behind its checks)
POWER_RTOL = {torch.float64: 1e-9, torch.float32: 1e-4}
# periodic power cells for cases up to this size: a dense layer on a periodic face
# is padded with its images, and its tall cells read every point (minutes a case)
PERIODIC_POWER_MAX_N = 5000


def case_weights(case, spread: float, rng) -> np.ndarray:
    """(N,) float64 weights representable in the case's dtype."""
    weights = np.zeros(case.n)
    for _cloud, members, (lo, hi) in case.clouds():
        spacing2 = (float(np.prod(np.maximum(hi - lo, 0.0))) / max(len(members), 1)) ** (2.0 / 3.0)
        weights[members] = rng.uniform(0.0, spread * spacing2, size=len(members))
    return weights.astype(np.float32 if case.dtype == torch.float32 else np.float64).astype(np.float64)


def check_power(campaign, case, shared: Dict) -> None:
    kind, dtype = case.kind, case.dtype
    spread = SPREADS[case.index % len(SPREADS)]
    rng = np.random.default_rng([case.seed, case.index, 11])
    weights = case_weights(case, spread, rng)
    try:
        points, box, batch = case.arguments(campaign.device)
        w = torch.tensor(weights, dtype=dtype).to(campaign.device)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cells = torchvor.voronoi(points, box, batch=batch, weights=w, on_failure="flag")
    except Exception as error:  # noqa: BLE001 - every exception is a finding
        campaign.report.add(kind, "unexpected_exceptions")
        campaign.problem(case, "power", "unexpected_exception",
                         f"power (spread {spread}): " + "".join(traceback.format_exception_only(type(error),
                                                                                                  error)).strip())
        return
    campaign.report.add(kind, "power_cells", case.n)
    if check_power_cells(campaign, case, cells, weights, spread, rng, None) and case.n <= PERIODIC_POWER_MAX_N:
        check_periodic_power(campaign, case, weights, spread, rng)


def check_periodic_power(campaign, case, weights: np.ndarray, spread: float, rng) -> None:
    """The case's power cells with its boxes periodic along AXES (by turns)."""
    axes = AXES[(case.index // len(SPREADS)) % len(AXES)]
    try:
        points, _box, batch = case.arguments(campaign.device)
        boxes = torch.tensor(case.boxes, dtype=case.dtype).to(campaign.device)
        w = torch.tensor(weights, dtype=case.dtype).to(campaign.device)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            cells = torchvor.voronoi(points, boxes if batch is not None else boxes[0], batch=batch, weights=w,
                                     periodic=axes, on_failure="flag")
    except Exception as error:  # noqa: BLE001 - every exception is a finding
        campaign.report.add(case.kind, "unexpected_exceptions")
        campaign.problem(case, "power", "unexpected_exception",
                         f"periodic {axes} power (spread {spread}): "
                         + "".join(traceback.format_exception_only(type(error), error)).strip())
        return
    campaign.report.add(case.kind, "power_cells", case.n)
    check_power_cells(campaign, case, cells, weights, spread, rng, axes)


def check_power_cells(campaign, case, cells, weights: np.ndarray, spread: float, rng, axes) -> bool:
    """Statuses, volume sums and sampled cells of a power call (periodic
    along `axes`, or not where None); False where cells failed."""
    from fuzz import SUM_RTOL  # fuzz.py imports this module

    kind, dtype = case.kind, case.dtype
    what = f"power (spread {spread})" if axes is None else f"periodic {axes} power (spread {spread})"
    volume = cells.volume.cpu().double().numpy()
    status = cells.status.cpu().numpy()
    ok = (status == CellStatus.SUCCESS) | (status == CellStatus.DUPLICATE) | (status == CellStatus.EMPTY)
    if not ok.all():
        campaign.report.add(kind, "failed_cells", int((~ok).sum()))
        campaign.problem(case, "power", "failed", f"{what}: {int((~ok).sum())} cells failed "
                                                  f"(statuses {sorted(set(status[~ok].tolist()))})")
        return False
    for cloud, members, (lo, hi) in case.clouds():
        expected = float(np.prod(hi - lo))
        got = volume[members].sum()
        cloud_points = case.points[members].astype(np.float64)
        if axes is not None:
            cloud_points = wrapped(cloud_points, lo, hi, axes)
        if not abs(got - expected) <= SUM_RTOL[dtype] * expected:
            if axes is not None and images_round(lo, hi, axes) and near_pair_across_a_face(cloud_points, lo, hi,
                                                                                            axes):
                campaign.note("periodic volume sum off: a near pair across a face, images rounded (api.md)")
            else:
                campaign.report.add(kind, "wrong_volume_sums")
                campaign.problem(case, "power", "volume_sum",
                                 f"{what}, cloud {cloud}: volumes sum to {got!r}, the box's is {expected!r}")
        if len(members) > (POWER_ORACLE_MAX_N if axes is None else PERIODIC_ORACLE_MAX_N):
            continue
        for local in rng.choice(len(members), size=min(POWER_SAMPLE, len(members)), replace=False):
            try:
                if axes is None:
                    oracle = voronoi_cell_oracle(cloud_points, int(local), (lo, hi), weights=weights[members])
                else:
                    oracle = periodic_cell_oracle(cloud_points, int(local), (lo, hi), axes, weights=weights[members])
            except Exception as error:  # noqa: BLE001 - Qhull's limits, not torchvor's
                campaign.report.add(kind, "oracle_skipped")
                campaign.note(f"power oracle error: {type(error).__name__}")
                continue
            row = int(members[local])
            mine, code = volume[row], int(status[row])
            tiny = 1e-12 * expected  # the oracle's linprog cannot tell an empty cell from one this small
            if oracle.empty or oracle.duplicate or oracle.volume <= tiny:
                good = mine <= tiny  # EMPTY, DUPLICATE, or a SUCCESS sliver as small
            else:
                good = code == CellStatus.SUCCESS and abs(mine - oracle.volume) <= POWER_RTOL[dtype] * oracle.volume
                if code == CellStatus.SUCCESS and not good:  # Qhull's own error on slivers: the exact oracle decides
                    exact = _exact_volume(cloud_points, int(local), lo, hi, axes, weights[members])
                    good = exact is not None and abs(mine - exact) <= POWER_RTOL[dtype] * exact
            if good:
                campaign.report.add(kind, "power_certified")
            else:
                campaign.report.add(kind, "silently_wrong")
                campaign.problem(case, "power", "power",
                                 f"{what}, cell {row}: volume {mine!r} status {code}, oracle "
                                 f"{oracle.volume!r} (empty {oracle.empty}, duplicate {oracle.duplicate})")
                return False
    return True


def _exact_volume(points: np.ndarray, i: int, lo, hi, axes, weights: np.ndarray):
    """The exact oracle's volume of power cell i (over the images where
    `axes`), from its 60 nearest points; None where it cannot."""
    if axes is not None:
        return exact_over_images(points, i, lo, hi, axes, weights=weights)
    nearest = [int(j) for j in np.argsort(((points - points[i]) ** 2).sum(1))[:61] if j != i]
    try:
        return exact_cell_oracle(points, i, (lo, hi), candidates=nearest, weights=weights).volume
    except Exception:  # noqa: BLE001 - more facets than the exact oracle takes
        return None
