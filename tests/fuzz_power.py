"""The fuzzing campaign's checks of power diagrams (tests/fuzz.py calls
check_power on every case small enough): the case's cells with weights (by
turns: equal, small, about the spacing's square, five times that, each
cloud's own scale), every cell computed (SUCCESS, DUPLICATE or EMPTY), each
cloud's volumes summing to its box's, and sampled cells against the
half-space oracle with power bisectors (empty ones included)."""
from __future__ import annotations

import traceback
import warnings
from typing import Dict

import numpy as np
import torch

import torchvor
from torchvor import CellStatus

from oracles import voronoi_cell_oracle

POWER_SAMPLE = 3            # cells of a case whose power cell goes to the oracle
POWER_ORACLE_MAX_N = 3000   # clouds up to this size (the oracle takes every point's plane)
SPREADS = (0.0, 0.1, 1.0, 5.0)  # weights uniform in [0, spread * s^2], s the cloud's mean spacing
# power cells are float64 whatever the points' dtype: the outputs' rounding bounds them
POWER_RTOL = {torch.float64: 1e-9, torch.float32: 1e-6}


def case_weights(case, spread: float, rng) -> np.ndarray:
    """(N,) float64 weights representable in the case's dtype."""
    weights = np.zeros(case.n)
    for _cloud, members, (lo, hi) in case.clouds():
        spacing2 = (float(np.prod(np.maximum(hi - lo, 0.0))) / max(len(members), 1)) ** (2.0 / 3.0)
        weights[members] = rng.uniform(0.0, spread * spacing2, size=len(members))
    return weights.astype(np.float32 if case.dtype == torch.float32 else np.float64).astype(np.float64)


def check_power(campaign, case, shared: Dict) -> None:
    from fuzz import SUM_RTOL  # fuzz.py imports this module

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
    volume = cells.volume.cpu().double().numpy()
    status = cells.status.cpu().numpy()
    ok = (status == CellStatus.SUCCESS) | (status == CellStatus.DUPLICATE) | (status == CellStatus.EMPTY)
    if not ok.all():
        campaign.report.add(kind, "failed_cells", int((~ok).sum()))
        campaign.problem(case, "power", "failed", f"power (spread {spread}): {int((~ok).sum())} cells failed "
                                                  f"(statuses {sorted(set(status[~ok].tolist()))})")
        return
    for cloud, members, (lo, hi) in case.clouds():
        expected = float(np.prod(hi - lo))
        got = volume[members].sum()
        if not abs(got - expected) <= SUM_RTOL[dtype] * expected:
            campaign.report.add(kind, "wrong_volume_sums")
            campaign.problem(case, "power", "volume_sum",
                             f"power (spread {spread}), cloud {cloud}: volumes sum to {got!r}, the box's is "
                             f"{expected!r}")
        if len(members) > POWER_ORACLE_MAX_N:
            continue
        cloud_points = case.points[members].astype(np.float64)
        for local in rng.choice(len(members), size=min(POWER_SAMPLE, len(members)), replace=False):
            try:
                oracle = voronoi_cell_oracle(cloud_points, int(local), (lo, hi), weights=weights[members])
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
            if good:
                campaign.report.add(kind, "power_certified")
            else:
                campaign.report.add(kind, "silently_wrong")
                campaign.problem(case, "power", "power",
                                 f"power (spread {spread}), cell {row}: volume {mine!r} status {code}, oracle "
                                 f"{oracle.volume!r} (empty {oracle.empty}, duplicate {oracle.duplicate})")
                return
