"""The fuzzing campaign's checks of torchvor.voronoi_graph (tests/fuzz.py calls
check_graph on every case small enough): the graph's structure, its faces
closing, the walls tiling each box, and sampled cells' faces against the
Qhull oracle, the exact oracle deciding where they disagree."""
from __future__ import annotations

import traceback
import warnings
from typing import Dict

import numpy as np

import torchvor
from torchvor import CellStatus

from oracles import voronoi_cell_oracle

GRAPH_SAMPLE = 3  # cells of a case's graph whose faces go to the oracle


def check_graph(campaign, case, shared: Dict) -> None:
    """torchvor.voronoi_graph of the case: its edges sorted, without self loops or
    edges between clouds, each face both ways with the same values; every
    SUCCESS cell's faces closed (the sum of area times outward normal, walls
    included, zero to the dtype's tolerance of its surface); each cloud's
    wall areas summing to its box's surface; and GRAPH_SAMPLE cells' faces
    against the Qhull oracle's (areas to 10 x the tolerance of the cell's
    surface)."""
    from fuzz import CELL_RTOL, SUM_RTOL  # fuzz.py imports this module

    kind, dtype = case.kind, case.dtype
    try:
        points, box, batch = case.arguments(campaign.device)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            graph = torchvor.voronoi_graph(points, box, batch=batch, on_failure="flag")
    except Exception as error:  # noqa: BLE001 - every exception is a finding
        campaign.report.add(kind, "unexpected_exceptions")
        campaign.problem(case, "graph", "unexpected_exception",
                         "voronoi_graph: " + "".join(traceback.format_exception_only(type(error), error)).strip())
        return
    campaign.report.add(kind, "graphs")
    n = case.n
    source, target = (t.cpu().numpy() for t in graph.edge_index)
    area = graph.area.cpu().double().numpy()
    centroid = graph.centroid.cpu().double().numpy()
    walls = graph.wall_area.cpu().double().numpy()
    status = graph.cells.status.cpu().numpy()
    cloud_of = np.zeros(n, dtype=np.int64) if case.batch is None else case.batch
    key = target.astype(np.int64) * n + source
    reverse = source.astype(np.int64) * n + target
    at = np.minimum(np.searchsorted(key, reverse), max(len(key) - 1, 0))
    wrong = []
    if len(key) and not (np.all(key[1:] > key[:-1]) and np.all(source != target) and np.all(area > 0)):
        wrong.append("edges not sorted, a self loop or a face of no area")
    if len(key) and not (np.array_equal(key[at], reverse) and np.array_equal(area[at], area)
                         and np.array_equal(centroid[at], centroid)):
        wrong.append("a face not the same both ways")
    if len(key) and np.any(cloud_of[source] != cloud_of[target]):
        wrong.append("an edge between two clouds")
    p = case.points.astype(np.float64)
    normal = p[source] - p[target]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    total = np.zeros((n, 3))
    np.add.at(total, target, area[:, None] * normal)
    total += np.stack([walls[:, 1] - walls[:, 0], walls[:, 3] - walls[:, 2], walls[:, 5] - walls[:, 4]], 1)
    surface = np.bincount(target, weights=area, minlength=n) + walls.sum(1)
    ok = status == CellStatus.SUCCESS
    with np.errstate(divide="ignore", invalid="ignore"):
        closure = np.where(ok, np.linalg.norm(total, axis=1) / surface, 0.0)
    open_cells = np.nonzero(~(closure <= CELL_RTOL[dtype]))[0]
    if len(open_cells):
        wrong.append(f"{len(open_cells)} cells whose faces do not close (worst {np.nanmax(closure):.2e} of their "
                     f"surface): cells {open_cells[:10].tolist()}")
    for cloud, members, (lo, hi) in case.clouds():
        if not ok[members].all():
            continue
        extent = hi - lo
        expected = 2 * (extent[0] * extent[1] + extent[1] * extent[2] + extent[0] * extent[2])
        got = walls[members].sum()
        if not abs(got - expected) <= SUM_RTOL[dtype] * expected:
            wrong.append(f"cloud {cloud}: the wall areas sum to {got!r}, its box's surface is {expected!r}")
    for message in wrong:
        campaign.report.add(kind, "silently_wrong")
        campaign.problem(case, "graph", "graph", message)
    check_faces(campaign, case, source, target, area, walls, ok, shared)

def check_faces(campaign, case, source, target, area, walls, ok, shared: Dict) -> None:
    """GRAPH_SAMPLE random SUCCESS cells' faces against the Qhull oracle's,
    the exact oracle deciding where they disagree."""
    from scipy.spatial import cKDTree

    from fuzz import CELL_RTOL, OracleSkipped, _Oracles, local_candidates, without_copies

    kind, dtype = case.kind, case.dtype
    rng = np.random.default_rng([case.seed, case.index, 2])
    candidates = np.nonzero(ok)[0]
    cloud_of = np.zeros(case.n, dtype=np.int64) if case.batch is None else case.batch
    clouds = {k: (members, box) for k, members, box in case.clouds()}
    oracle = _Oracles(campaign.exact_max_facets)
    for i in rng.choice(candidates, size=min(GRAPH_SAMPLE, len(candidates)), replace=False):
        i = int(i)
        members, (lo, hi) = clouds[int(cloud_of[i])]
        if int(cloud_of[i]) not in shared:
            shared[int(cloud_of[i])] = cKDTree(case.points[members])
        local = int(np.searchsorted(members, i))
        on = target == i
        got = {int(j): float(a) for j, a in zip(source[on], area[on])}
        got.update({-1 - w: float(walls[i, w]) for w in range(6) if walls[i, w] > 0})

        def off(reference, sub):
            """The largest face area difference, and the reference's surface."""
            expected = {(int(members[sub[key]]) if key >= 0 else key): value[0]
                        for key, value in reference.faces.items()}
            worst = max(abs(got.get(key, 0.0) - expected.get(key, 0.0)) for key in set(got) | set(expected))
            return worst, reference.area, sorted(expected)[:12]

        try:
            sub = local_candidates(oracle, shared[int(cloud_of[i])], case.points[members], local, (lo, hi),
                                   campaign.oracle_max_points)
            sub = without_copies(case.points[members], sub, local)
            points = case.points[members][sub].astype(np.float64)
            pos = int(np.searchsorted(sub, local))
            worst, surface, names = off(voronoi_cell_oracle(points, pos, (lo, hi)), sub)
            if not worst <= 10 * CELL_RTOL[dtype] * surface:
                worst, surface, names = off(oracle.arbiter(points, pos, (lo, hi)), sub)
        except OracleSkipped as error:
            campaign._skip(f"faces: {error}")
            continue
        except Exception as error:  # noqa: BLE001 - the oracle's own failures (Qhull)
            campaign._skip(f"faces: oracle error: {type(error).__name__}")
            continue
        if worst <= 10 * CELL_RTOL[dtype] * surface:
            campaign.report.add(kind, "faces_certified")
            continue
        campaign.report.add(kind, "silently_wrong")
        campaign.problem(case, "graph", "graph_faces", f"cell {i}: a face area off by {worst!r} (the oracle's "
                         f"surface {surface!r}); faces {sorted(got)[:12]} vs the oracle's {names}", cell=i)
    for text, count in oracle.notes.items():
        campaign.report.oracle_notes[text] = campaign.report.oracle_notes.get(text, 0) + count
