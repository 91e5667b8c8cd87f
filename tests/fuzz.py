"""Fuzzing campaign for torchvor.voronoi and voronoi_graph: point sets of
many kinds, every result checked against independent oracles.

The point sets come from tests/fuzz_cases.py. A campaign is a seed S and a
range of case indices. Case I is drawn from a numpy Generator seeded by
(S, I) alone, so any case replays on its own:

    python tests/fuzz.py --seed S --case I [--device cuda] [--dtype ...] [--max-n M]

The kinds of input (KINDS) take turns by case index; with ``--dtype both``
the dtype alternates every round of kinds. Every 41st case is a deliberately
invalid input (a flat or inverted box, a point outside its box, a NaN),
which must raise a ValueError naming the cause.

Each case runs once per cell implementation asked for (``--cells``: the
backend's default, TORCHVOR_CELLS=thread, =cooperative, or "all": both) and
is checked for:

* no exception (for a valid input), and the expected ValueError (invalid);
* every cell SUCCESS or DUPLICATE, with finite, non-negative outputs;
* DUPLICATE exactly on the exact copies of a lower-index point of the same
  cloud (all cells: a numpy comparison of the coordinates);
* the volumes of each cloud summing to its box volume (float64 1e-9
  relative, float32 1e-4);
* a sample of cells (the largest, those that needed the most neighbours,
  random ones, and in float32 the few whose volumes differ most from
  torchvor's float64 cells of the same points) against the Qhull oracle of
  tests/oracles.py on the float64 copy of the same coordinates, with the
  exact rational oracle deciding where Qhull disagrees
  (voronoi_checks.check_against_oracle): the volume within 1e-9 (float64)
  or 1e-4 (float32) relative, the centroid within as much of the cell's
  size plus the rounding of its absolute coordinates to the output dtype
  (outside: silently wrong); the second moment within the same relative
  tolerance (outside, with volume and centroid inside: reported as
  second_moment, which does not fail the campaign);
* on CUDA, for clouds small enough, the same statuses as the CPU's and
  volumes within the same relative tolerance;
* for cases of at most ``--graph-max-n`` points, torchvor.voronoi_graph
  (check_graph): edges sorted, each face both ways with the same values, no
  edge between clouds; every cell's faces closed (area times outward normal,
  walls included, summing to zero within the tolerance of its surface); each
  cloud's wall areas tiling its box's surface; and GRAPH_SAMPLE cells' face
  areas within 10 x the tolerance of the oracle's (exact where Qhull
  disagrees) (faces_certified);
* for the same cases, the cells with the boxes periodic along some axes by
  turns (fuzz_periodic.py): every cell computed, each cloud's volumes summing
  to its box's, and PERIODIC_SAMPLE cells against the half-space oracle over
  the points' images (periodic_certified);
* for the same cases, the power cells with weights of several scales
  (fuzz_power.py): every cell computed or EMPTY, each cloud's volumes
  summing to its box's, and POWER_SAMPLE cells against the half-space oracle
  with power bisectors (power_certified).

The oracle sees only the points near a cell: the nearest K of its cloud
(cKDTree), K growing until the (K+1)-th lies beyond twice the radius of the
Qhull cell of those K (then no other point can cut the cell; a Qhull cell of
no volume settles nothing). Where Qhull
cannot build a cell (a box 1e-7 thin, a cell many orders of magnitude
smaller than its box), it builds it on the input scaled to a unit box, or
in a small box around the seed (_Oracles). Cells the oracles cannot decide
within bounds are counted as skipped, with the reason.

Exit status 1 if any cell failed, any cell was silently wrong (or a cloud's
volumes did not sum to its box), an unexpected exception was raised, or a
case ran past --case-timeout (the campaign stops there). ``--time-budget S``
starts no case after S seconds, so that a campaign fits a bounded call (the
summary counts the cases that ran). ``--workers W`` runs the cases in W
processes, each claiming the next case of the range when it is free (so a
budgeted campaign runs a prefix of the range, every kind in turn), and
reports them as one.
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import os
import re
import sys
import time
import traceback
import warnings
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Sequence

import numpy as np
import torch

if __package__ in (None, ""):
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import torchvor  # noqa: E402
from torchvor import CellStatus  # noqa: E402

import fuzz_graph  # noqa: E402
import fuzz_periodic  # noqa: E402
import fuzz_power  # noqa: E402
import voronoi_checks  # noqa: E402
from oracles import voronoi_cell_oracle  # noqa: E402

from fuzz_cases import DTYPE_NAMES, INVALID_EVERY, KINDS, Case, make_case  # noqa: E402,F401  (the tests use them here)
from fuzz_workers import ClaimedCases, run_workers  # noqa: E402
# the guarantee a SUCCESS cell is held to (relative volume; centroid relative to the cell size)
CELL_RTOL = {torch.float64: 1e-9, torch.float32: 1e-4}
# the sum of a cloud's volumes, relative to its box volume
SUM_RTOL = {torch.float64: 1e-9, torch.float32: 1e-4}
CELL_IMPLS = ("default", "thread", "cooperative")  # "all" runs thread and cooperative
EXACT_MAX_FACETS = 1000  # the most Qhull facets a cell may have for the exact oracle to arbitrate it
SLOWEST_CASES = 5  # the report lists the slowest cases (their time covers the checks too)
COUNTERS = ("cases", "runs", "cells", "certified", "oracle_skipped", "failed_cells", "silently_wrong",
            "wrong_volume_sums", "unexpected_exceptions", "timeouts", "expected_errors", "second_moment_off",
            "graphs", "faces_certified", "periodic_cells", "periodic_certified", "power_cells", "power_certified")
# any of these makes a campaign fail. second_moment_off (a cell whose volume and centroid are
# within the guarantee, its second moment outside the same relative tolerance) is reported only.
FAILURES = ("failed_cells", "silently_wrong", "wrong_volume_sums", "unexpected_exceptions", "timeouts")


# ---------------------------------------------------------------------------- checking


class OracleSkipped(Exception):
    """The oracle cannot decide this cell within the fuzzer's bounds."""


@contextlib.contextmanager
def _cells_impl(impl: str):
    """TORCHVOR_CELLS set to `impl` ("default": unset) for the duration."""
    old = os.environ.get("TORCHVOR_CELLS")
    if impl == "default":
        os.environ.pop("TORCHVOR_CELLS", None)
    else:
        os.environ["TORCHVOR_CELLS"] = impl
    try:
        yield
    finally:
        if old is None:
            os.environ.pop("TORCHVOR_CELLS", None)
        else:
            os.environ["TORCHVOR_CELLS"] = old


def _scaled_oracle(points, i, box):
    """voronoi_cell_oracle on the input scaled by the power of two that makes
    the box's smallest extent 1 to 2 (exact: Voronoi cells scale with it),
    its results scaled back; None if Qhull fails there too. For thin boxes,
    whose cells leave Qhull's feasible point within its tolerance of a wall."""
    p = np.asarray(points, dtype=np.float64)
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box)
    k = -int(math.floor(math.log2(float((hi - lo).min()))))
    if k == 0:
        return None
    try:
        ref = voronoi_cell_oracle(np.ldexp(p, k), i, (np.ldexp(lo, k), np.ldexp(hi, k)))
    except Exception:  # noqa: BLE001
        return None
    return dataclasses.replace(ref, volume=math.ldexp(ref.volume, -3 * k), centroid=np.ldexp(ref.centroid, -k),
                               second_moment=math.ldexp(ref.second_moment, -5 * k),
                               vertices=np.ldexp(ref.vertices, -k), seed=np.ldexp(ref.seed, -k),
                               area=math.ldexp(ref.area, -2 * k))


def _oracle_in_local_box(points, i, box):
    """The cell of point i from the points within 2 sqrt(3) h of it, in the
    real box cut to the cube of half-width h around the seed (scaled as
    _scaled_oracle where plain Qhull fails), with h doubling from the nearest
    distance until no vertex lies on a wall of the cube that is not a wall
    of the real box (then it is the cell in the real box). None if that
    fails. For cells many orders of magnitude smaller than the box."""
    p = np.asarray(points, dtype=np.float64)
    lo, hi = (np.asarray(b, dtype=np.float64).reshape(3) for b in box)
    seed = p[i]
    dist = np.sqrt(((p - seed) ** 2).sum(1))
    positive = dist[dist > 0]
    if len(positive) == 0:
        return None
    h = float(positive.min())
    for _ in range(200):
        llo, lhi = np.maximum(lo, seed - h), np.minimum(hi, seed + h)
        artificial_lo, artificial_hi = llo > lo, lhi < hi
        if not (artificial_lo.any() or artificial_hi.any()):
            return None  # the cube covers the real box, where Qhull failed
        near = np.nonzero(dist <= 2 * math.sqrt(3) * h * (1 + 1e-9))[0]
        local = int(np.searchsorted(near, i))
        try:
            ref = voronoi_cell_oracle(p[near], local, (llo, lhi))
        except Exception:  # noqa: BLE001
            ref = _scaled_oracle(p[near], local, (llo, lhi))
        if ref is not None:
            margin = 1e-7 * h
            v = ref.vertices
            touches = ((artificial_lo & (v <= llo + margin).any(0)).any()
                       or (artificial_hi & (v >= lhi - margin).any(0)).any())
            if not touches:
                return dataclasses.replace(ref, facet_neighbors=near[ref.facet_neighbors])
        h *= 2
    return None


class _Oracles:
    """The oracles check_against_oracle uses, for the fuzzer.

    Qhull (voronoi_cell_oracle). Where Qhull cannot build a cell (its
    tolerances and linprog's follow the box, so the feasible point of a cell
    1e-10 wide in a unit box, or of any cell in a box 1e-7 thin, is not
    "clearly inside"), Qhull on the input scaled to a unit box, then in a
    small box around the seed (_scaled_oracle, _oracle_in_local_box). The
    exact oracle arbitrates where Qhull disagrees with torchvor, refusing
    (OracleSkipped) cells whose Qhull cell has more than `max_facets` facets
    (its time grows with them). `notes` counts these fallbacks."""

    def __init__(self, max_facets: int):
        self.max_facets = max_facets
        self.notes: Dict[str, int] = {}
        self.exact = voronoi_checks.exact_cell_oracle

    def note(self, text: str) -> None:
        self.notes[text] = self.notes.get(text, 0) + 1

    def qhull(self, points, i, box):
        try:
            return voronoi_cell_oracle(points, i, box)
        except Exception as error:  # noqa: BLE001 - QhullError, or linprog's empty cell
            for name, fallback in (("scaled to a unit box", _scaled_oracle),
                                   ("solved in a box around the seed", _oracle_in_local_box)):
                ref = fallback(points, i, box)
                if ref is not None:
                    self.note(f"Qhull failed in the box ({type(error).__name__}), {name}")
                    return ref
            raise

    def arbiter(self, points, i, box, candidates=None):
        if candidates is None:
            candidates = self.qhull(points, i, box).facet_neighbors
        if len(candidates) > self.max_facets:
            raise OracleSkipped(f"Qhull disagrees with the cell beyond the tolerance and the exact oracle "
                                f"would need {len(candidates)} facets (more than {self.max_facets}): undecided")
        self.note("Qhull disagreed, exact oracle decided")
        return self.exact(points, i, box, candidates)

    @contextlib.contextmanager
    def installed(self):
        """These oracles in voronoi_checks (check_against_oracle's) for the duration."""
        saved = voronoi_checks.voronoi_cell_oracle, voronoi_checks.exact_cell_oracle
        voronoi_checks.voronoi_cell_oracle, voronoi_checks.exact_cell_oracle = self.qhull, self.arbiter
        try:
            yield self
        finally:
            voronoi_checks.voronoi_cell_oracle, voronoi_checks.exact_cell_oracle = saved


def local_candidates(oracle: _Oracles, tree, points: np.ndarray, i: int, box, max_points: int) -> np.ndarray:
    """Indices (sorted, into `points` of one cloud) of the nearest K points
    to point i plus i itself, with K grown until the next point lies at least
    twice the radius of the oracle's cell of those K away (so no other point
    can cut the cell; a cell of no volume never settles it), or all points.
    Raises OracleSkipped beyond max_points."""
    n = len(points)
    k = min(n, 64)
    while True:
        dist, idx = tree.query(points[i], k=k)
        idx = np.atleast_1d(idx)
        dist = np.atleast_1d(dist)
        sub = np.unique(np.append(idx, i))
        if k >= n:
            return sub
        pos = int(np.searchsorted(sub, i))
        ref = oracle.qhull(points[sub], pos, box)
        # A cell of no volume (Qhull lost a cell a few thousand ulps wide) has no
        # radius to trust: more points, up to all of them.
        if ref.duplicate or (ref.volume > 0 and dist[-1] >= 2 * ref.radius * (1 + 1e-6)):
            return sub
        if k >= max_points:
            raise OracleSkipped(f"the cell needs more than {max_points} candidate points")
        k = min(n, 4 * k, max_points)


def without_copies(points: np.ndarray, sub: np.ndarray, i: int) -> np.ndarray:
    """`sub` (sorted indices into `points`) keeping only the first of each
    set of exact copies, and `i`: the cell of point i is the same (copies of
    a neighbour cut it along the same plane; a lower-index copy of point i
    stays). The exact oracle counts a face once per plane, so a copy of a
    neighbour among its candidates would count that face twice."""
    p = points[sub] + 0.0
    order = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))  # stable: copies by increasing index
    same = np.zeros(len(sub), dtype=bool)
    same[1:] = np.all(p[order][1:] == p[order][:-1], axis=1)
    copy = np.empty(len(sub), dtype=bool)
    copy[order] = same
    return sub[~copy | (sub == i)]


def pick_sample(cells, ok: np.ndarray, count: int, rng, suspects: Sequence[int] = ()) -> List[int]:
    """Up to `count` cells among `ok`: a quarter the largest, a quarter those
    that needed the most neighbours, the rest random; plus `suspects`."""
    candidates = np.nonzero(ok)[0]
    if len(candidates) <= count:
        return sorted(set(candidates.tolist()) | set(int(j) for j in suspects))
    volume = cells.volume.double().numpy()[candidates]
    needed = cells.neighbors_needed.numpy()[candidates]
    chosen = list(candidates[np.argsort(-volume, kind="stable")[: count // 4]])
    for j in candidates[np.argsort(-needed, kind="stable")]:
        if len(chosen) >= 2 * (count // 4):
            break
        if j not in chosen:
            chosen.append(j)
    taken = np.zeros(len(ok), dtype=bool)
    taken[np.asarray(chosen, dtype=np.int64)] = True
    rest = candidates[~taken[candidates]]  # as np.setdiff1d, without its sort
    chosen += list(rng.choice(rest, size=min(len(rest), count - len(chosen)), replace=False))
    return sorted(set(int(j) for j in chosen) | set(int(j) for j in suspects))


@dataclass
class Problem:
    case: int
    kind: str
    dtype: str
    device: str
    cells_impl: str
    # failed_cells, silently_wrong, wrong_volume_sum, unexpected_exception, timeout (these fail the
    # campaign); second_moment, undecided (reported only)
    category: str
    message: str
    replay: str
    cell: Optional[int] = None
    count: int = 1


@dataclass
class Report:
    """Counts (overall and per kind), problems and the settings of a campaign."""

    settings: Dict
    counts: Dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTERS, 0))
    per_kind: Dict[str, Dict[str, int]] = field(default_factory=dict)
    problems: List[Problem] = field(default_factory=list)
    skip_reasons: Dict[str, int] = field(default_factory=dict)
    oracle_notes: Dict[str, int] = field(default_factory=dict)
    slowest: List[Dict] = field(default_factory=list)  # the SLOWEST_CASES slowest cases, slowest first
    seconds: float = 0.0
    phase_seconds: Dict[str, float] = field(default_factory=dict)  # where the time goes (Campaign.timed)
    kind_seconds: Dict[str, float] = field(default_factory=dict)  # each kind's cases, checks included

    def add(self, kind: str, name: str, value: int = 1) -> None:
        self.counts[name] += value
        self.per_kind.setdefault(kind, dict.fromkeys(COUNTERS, 0))[name] += value

    def ok(self) -> bool:
        return all(self.counts[name] == 0 for name in FAILURES)

    def as_dict(self) -> Dict:
        return {"settings": self.settings, "counts": self.counts, "per_kind": self.per_kind,
                "oracle_skip_reasons": self.skip_reasons, "oracle_notes": self.oracle_notes,
                "slowest": self.slowest, "seconds": self.seconds, "phase_seconds": self.phase_seconds,
                "kind_seconds": self.kind_seconds,
                "problems": [vars(p) for p in self.problems]}


def replay_command(case: Case, settings: Dict, impl: Optional[str] = None) -> str:
    parts = ["python tests/fuzz.py", f"--seed {case.seed}", f"--case {case.index}",
             f"--device {settings['device']}", f"--dtype {settings['dtype']}", f"--max-n {settings['max_n']}",
             # the graph's checks run with every --cells (one thread cell each)
             f"--cells {impl if impl in ('thread', 'cooperative') else settings['cells']}"]
    if settings.get("kinds"):
        parts.append("--kinds " + ",".join(settings["kinds"]))
    for name, default in (("sample", 12), ("suspects", 4)):
        if settings.get(name, default) != default:
            parts.append(f"--{name} {settings[name]}")
    return " ".join(parts)


def _exact_copies(case: Case) -> np.ndarray:
    """(N,) bool: whether each point is an exact copy of a lower index of its
    cloud (computed once a case: a lexicographic sort of the points)."""
    if case.n == 0:
        return np.zeros(0, dtype=bool)
    cloud = np.zeros(case.n, dtype=np.int64) if case.batch is None else case.batch
    p = case.points + 0.0  # -0.0 and 0.0 are the same point
    order = np.lexsort((p[:, 2], p[:, 1], p[:, 0], cloud))  # stable: equal points by increasing index
    q, c = p[order], cloud[order]
    same = np.zeros(case.n, dtype=bool)
    same[1:] = (c[1:] == c[:-1]) & np.all(q[1:] == q[:-1], axis=1)
    is_copy = np.empty(case.n, dtype=bool)
    is_copy[order] = same
    return is_copy


def _duplicate_mismatch(is_copy: np.ndarray, status: np.ndarray) -> np.ndarray:
    """Cells whose DUPLICATE status disagrees with the coordinates (`is_copy`,
    _exact_copies): a cell is a duplicate exactly when a lower index of its
    cloud has the same point."""
    claimed = status == CellStatus.DUPLICATE
    ok = (status == CellStatus.SUCCESS) | claimed
    return np.nonzero(ok & (claimed != is_copy))[0]


class Campaign:
    """Runs cases and accumulates a Report. `cells` is "default", "thread",
    "cooperative" or "all"; `sample` cells a run go to the oracle; on CUDA,
    clouds of at most `compare_max_n` points are also compared with the CPU."""

    current = None  # (case index, start time) of the case running
    current_impl = "default"  # and the cell implementation it runs under

    def __init__(self, seed=0, *, device="cpu", max_n=20000, dtype="both", cells="default", sample=12, suspects=4,
                 kinds=None, compare_max_n=20000, oracle_max_points=50000, exact_max_facets=EXACT_MAX_FACETS,
                 graph_max_n=20000, out=None):
        self.seed = seed
        self.device = torch.device(device)
        self.max_n, self.dtype, self.sample, self.suspects = max_n, dtype, sample, suspects
        self.impls = ["thread", "cooperative"] if cells == "all" else [cells]
        self.kinds = list(kinds) if kinds else None
        self.compare_max_n, self.oracle_max_points = compare_max_n, oracle_max_points
        self.exact_max_facets = exact_max_facets
        self.graph_max_n = graph_max_n
        self.out = out
        settings = {"seed": seed, "device": str(device), "max_n": max_n, "dtype": dtype, "cells": cells,
                    "sample": sample, "suspects": suspects, "kinds": self.kinds}
        self.report = Report(settings)

    @contextlib.contextmanager
    def timed(self, phase: str):
        """Adds the time spent inside to the report's phase_seconds[phase]."""
        t0 = time.perf_counter()
        try:
            yield
        finally:
            seconds = self.report.phase_seconds
            seconds[phase] = seconds.get(phase, 0.0) + time.perf_counter() - t0

    def log(self, text: str) -> None:
        if self.out is not None:
            print(text, file=self.out, flush=True)

    def note(self, text: str) -> None:
        """Counts a remark that is not a finding (the oracles' limits, documented limits)."""
        self.report.oracle_notes[text] = self.report.oracle_notes.get(text, 0) + 1

    def problem(self, case: Case, impl: str, category: str, message: str, cell=None, count=1) -> None:
        p = Problem(case.index, case.kind, DTYPE_NAMES[case.dtype], str(self.device), impl, category, message,
                    replay_command(case, self.report.settings, impl), cell, count)
        self.report.problems.append(p)
        self.log(f"  PROBLEM [{category}] {case.describe()}, cells={impl}: {message}\n    replay: {p.replay}")

    def run(self, indices: Sequence[int], time_budget: float = 0.0,
            after_case: Optional[Callable[[Report], None]] = None) -> Report:
        """Runs the cases `indices` in order; with `time_budget` > 0 (seconds),
        starts no case once that much time has passed (the report's counts
        say how many ran). `after_case(report)` is called after each case."""
        start = time.perf_counter()
        seconds_before = self.report.seconds
        cases = iter(indices)  # taken only while the budget lasts (ClaimedCases: no case claimed and not run)
        while True:
            if time_budget > 0 and time.perf_counter() - start > time_budget:
                self.log(f"time budget of {time_budget:g} s spent: stopped")
                break
            index = next(cases, None)
            if index is None:
                break
            self.current = (int(index), time.perf_counter())
            self.run_case(int(index))
            self.current = None
            if after_case is not None:
                self.report.seconds = seconds_before + time.perf_counter() - start
                after_case(self.report)
        self.report.seconds = seconds_before + time.perf_counter() - start
        return self.report

    def watch(self, timeout: float, finish: Callable[[], None]) -> None:
        """Starts a thread that, once a case has run `timeout` seconds, records
        it as a timeout problem and calls `finish` (which must end the
        process: a running op cannot be interrupted)."""
        import threading

        def watchdog():
            while True:
                time.sleep(min(1.0, timeout))
                current = self.current
                if current is None or time.perf_counter() - current[1] < timeout:
                    continue
                case = make_case(self.seed, current[0], max_n=self.max_n, dtype=self.dtype, kinds=self.kinds)
                self.report.add(case.kind, "timeouts")
                self.problem(case, self.current_impl, "timeout",
                             f"the case ran for more than {timeout:g} s (the campaign stops here)")
                self.report.seconds += time.perf_counter() - current[1]
                finish()
                return

        self.current = None
        threading.Thread(target=watchdog, daemon=True).start()

    def run_case(self, index: int) -> None:
        """One case under every cell implementation asked for."""
        t0 = time.perf_counter()
        with self.timed("make_case"):
            case = make_case(self.seed, index, max_n=self.max_n, dtype=self.dtype, kinds=self.kinds)
        self.report.add(case.kind, "cases")
        shared = {}  # what the runs of a case share: its cKDTrees by cloud, its exact copies, its float64 cells
        before = {name: self.report.counts[name] for name in COUNTERS}
        for impl in self.impls:
            self.current_impl = impl
            self.run_one(case, impl, shared)
        if 0 < case.n <= self.graph_max_n and not case.expect_error:
            self.current_impl = "graph"
            with self.timed("graph"):
                self.check_graph(case, shared)
            self.current_impl = "periodic"
            with self.timed("periodic"):
                fuzz_periodic.check_periodic(self, case, shared)
            self.current_impl = "power"
            with self.timed("power"):
                fuzz_power.check_power(self, case, shared)
        seconds = time.perf_counter() - t0
        self.report.kind_seconds[case.kind] = self.report.kind_seconds.get(case.kind, 0.0) + seconds
        self.report.slowest.append({"seconds": round(seconds, 2), "case": case.describe(),
                                    "replay": replay_command(case, self.report.settings)})
        self.report.slowest.sort(key=lambda entry: -entry["seconds"])
        del self.report.slowest[SLOWEST_CASES:]
        delta = {name: self.report.counts[name] - before[name] for name in COUNTERS}
        bad = ", ".join(f"{name} {delta[name]}" for name in FAILURES if delta[name])
        self.log(f"{case.describe()}: {delta['certified']} certified, {delta['oracle_skipped']} skipped"
                 f"{', ' + bad if bad else ''} [{seconds:.1f} s]")

    def run_one(self, case: Case, impl: str, shared: Dict) -> None:
        """Runs torchvor.voronoi on `case` under `impl` and checks the result."""
        kind = case.kind
        self.report.add(kind, "runs")
        try:
            points, box, batch = case.arguments(self.device)
            with _cells_impl(impl), warnings.catch_warnings(), self.timed("voronoi"):
                warnings.simplefilter("ignore")
                cells = torchvor.voronoi(points, box, batch=batch, on_failure="flag")
                if self.device.type == "cuda":
                    torch.cuda.synchronize()
        except Exception as error:  # noqa: BLE001 - every exception is a finding
            if case.expect_error and isinstance(error, ValueError) and re.search(case.expect_error, str(error)):
                self.report.add(kind, "expected_errors")
                return
            self.report.add(kind, "unexpected_exceptions")
            self.problem(case, impl, "unexpected_exception",
                         "".join(traceback.format_exception_only(type(error), error)).strip())
            return
        if case.expect_error:
            self.report.add(kind, "unexpected_exceptions")
            self.problem(case, impl, "unexpected_exception",
                         f"an invalid input ({case.params.get('invalid')}) raised no ValueError "
                         f"matching {case.expect_error!r}")
            return
        self.report.add(kind, "cells", case.n)
        cpu = torchvor.VoronoiCells(*(t.cpu() for t in cells))
        self.check_cells(case, impl, cpu, shared)
        if self.device.type == "cuda":
            with self.timed("cpu_compare"):
                self.compare_with_cpu(case, impl, cpu)

    def check_cells(self, case: Case, impl: str, cells, shared: Dict) -> None:
        """Statuses, finite outputs, duplicates, volume sums, and the oracle sample."""
        kind, dtype = case.kind, case.dtype
        status = cells.status.numpy().astype(np.int64)
        ok = (status == CellStatus.SUCCESS) | (status == CellStatus.DUPLICATE)
        if not ok.all():
            bad = np.nonzero(~ok)[0]
            names = sorted({_status_name(s) for s in status[bad]})
            self.report.add(kind, "failed_cells", len(bad))
            self.problem(case, impl, "failed_cells", f"{len(bad)} cells failed ({', '.join(names)}): "
                         f"cells {bad[:10].tolist()}", cell=int(bad[0]), count=len(bad))
        vol = cells.volume.double().numpy()
        cen = cells.centroid.double().numpy()
        m2 = cells.second_moment.double().numpy()
        finite = np.isfinite(vol) & np.isfinite(m2) & np.isfinite(cen).all(1) & (vol >= 0) & (m2 >= 0)
        bad = np.nonzero(ok & ~finite)[0]
        if len(bad):
            self.report.add(kind, "silently_wrong", len(bad))
            self.problem(case, impl, "silently_wrong", f"{len(bad)} cells with status SUCCESS/DUPLICATE have "
                         f"non-finite or negative outputs: cells {bad[:10].tolist()}", cell=int(bad[0]),
                         count=len(bad))
        if "exact_copies" not in shared:  # the case's, for each of its runs
            with self.timed("exact_copies"):
                shared["exact_copies"] = _exact_copies(case)
        bad = _duplicate_mismatch(shared["exact_copies"], status)
        if len(bad):
            self.report.add(kind, "silently_wrong", len(bad))
            self.problem(case, impl, "silently_wrong", f"{len(bad)} cells whose DUPLICATE status disagrees with "
                         f"the coordinates (a duplicate is an exact copy of a lower index of its cloud): "
                         f"cells {bad[:10].tolist()}, status {status[bad[:10]].tolist()}", cell=int(bad[0]),
                         count=len(bad))
        for cloud, members, (lo, hi) in case.clouds():
            if not ok[members].all():
                continue
            box_volume = float(np.prod(hi - lo))
            total = float(np.sum(vol[members]))
            if not abs(total - box_volume) <= SUM_RTOL[dtype] * box_volume:
                self.report.add(kind, "wrong_volume_sums")
                self.problem(case, impl, "wrong_volume_sum",
                             f"cloud {cloud}: the volumes sum to {total!r}, its box's volume is {box_volume!r} "
                             f"(rel {abs(total / box_volume - 1):.2e}, tolerance {SUM_RTOL[dtype]:.0e})")
        with self.timed("float64_cells"):
            suspects = self.float32_suspects(case, cells, ok & finite, shared) if dtype == torch.float32 else []
        with self.timed("oracle"):
            self.check_sample(case, impl, cells, ok & finite, shared, suspects)

    def float32_suspects(self, case: Case, cells, ok: np.ndarray, shared: Dict) -> List[int]:
        """The `suspects` SUCCESS cells of a float32 run whose volumes differ
        most (relatively, beyond 1e-6) from torchvor's float64 cells of the
        same points (the default cells, computed once a case): candidates for
        the oracle, which decides."""
        if self.suspects <= 0 or case.n == 0:
            return []
        if "float64" not in shared:
            points, box, batch = case.arguments(self.device)
            if isinstance(box, torch.Tensor):
                box = box.double()
            with _cells_impl("default"), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                wide = torchvor.voronoi(points.double(), box, batch=batch, on_failure="flag")
            shared["float64"] = (wide.volume.cpu().numpy(), wide.status.cpu().numpy())
        v64, status64 = shared["float64"]
        v32 = cells.volume.double().numpy()
        both = ok & (cells.status.numpy() == CellStatus.SUCCESS) & (status64 == CellStatus.SUCCESS)
        with np.errstate(divide="ignore", invalid="ignore"):
            rel = np.where(both & (v64 > 0), np.abs(v32 / v64 - 1), 0.0)
        order = np.argsort(-rel, kind="stable")[: self.suspects]
        return [int(j) for j in order if rel[j] > 1e-6]

    def check_sample(self, case: Case, impl: str, cells, ok: np.ndarray, shared: Dict, suspects=()) -> None:
        """The sampled cells and `suspects` against the oracle
        (check_against_oracle on the cell's local candidates)."""
        from scipy.spatial import cKDTree

        kind, dtype = case.kind, case.dtype
        rng = np.random.default_rng([case.seed, case.index, 1])  # the same random cells under each impl
        cloud_of = np.zeros(case.n, dtype=np.int64) if case.batch is None else case.batch
        clouds = {k: (members, box) for k, members, box in case.clouds()}
        points_t = torch.tensor(case.points, dtype=dtype)
        oracle = _Oracles(self.exact_max_facets)
        with oracle.installed():
            for i in pick_sample(cells, ok, self.sample, rng, suspects):
                members, (lo, hi) = clouds[int(cloud_of[i])]
                if int(cloud_of[i]) not in shared:
                    shared[int(cloud_of[i])] = cKDTree(case.points[members])
                local = int(np.searchsorted(members, i))
                try:
                    sub = local_candidates(oracle, shared[int(cloud_of[i])], case.points[members], local, (lo, hi),
                                           self.oracle_max_points)
                    sub = without_copies(case.points[members], sub, local)
                    rows = torch.as_tensor(members[sub])
                    pos = int(np.searchsorted(sub, local))
                    view = torchvor.VoronoiCells(*(t[rows] for t in cells))
                    voronoi_checks.check_against_oracle(view, points_t[rows], (lo, hi), [pos], CELL_RTOL[dtype],
                                                        tag=f"cell {i}:")
                except AssertionError as error:
                    message = str(error).replace(f"cell {pos} (seed", "(seed")
                    # check_against_oracle tests volume, centroid, then second moment: only the
                    # last failed when the (exact) oracle's verdict names the second moment
                    category = "second_moment" if ": second moment " in message.split("; Qhull:")[0] else \
                        "silently_wrong"
                    self.report.add(kind, "second_moment_off" if category == "second_moment" else "silently_wrong")
                    state = (f"status {_status_name(int(cells.status[i]))}, "
                             f"neighbors_needed {int(cells.neighbors_needed[i])}")
                    self.problem(case, impl, category, f"{message} [{state}]", cell=i)
                    continue
                except OracleSkipped as error:
                    self.report.add(kind, "oracle_skipped")
                    self._skip(str(error))
                    if "undecided" in str(error):
                        self.problem(case, impl, "undecided", f"cell {i}: {error}", cell=i)
                    continue
                except Exception as error:  # noqa: BLE001 - the oracle's own failures (Qhull, linprog)
                    self.report.add(kind, "oracle_skipped")
                    self._skip(f"oracle error: {type(error).__name__}: {str(error).splitlines()[0][:100]}")
                    continue
                self.report.add(kind, "certified")
        for text, count in oracle.notes.items():
            self.report.oracle_notes[text] = self.report.oracle_notes.get(text, 0) + count

    def check_graph(self, case: Case, shared: Dict) -> None:
        """voronoi_graph of the case against its invariants and the oracles (fuzz_graph.py)."""
        fuzz_graph.check_graph(self, case, shared)

    def _skip(self, reason: str) -> None:
        self.report.skip_reasons[reason] = self.report.skip_reasons.get(reason, 0) + 1

    def compare_with_cpu(self, case: Case, impl: str, cells) -> None:
        """CUDA's statuses equal the CPU's and its volumes are within the
        dtype's tolerance of them (relative), for inputs of at most
        compare_max_n points."""
        if case.n > self.compare_max_n:
            return
        points, box, batch = case.arguments("cpu")
        with _cells_impl(impl), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ref = torchvor.voronoi(points, box, batch=batch, on_failure="flag")
        same = ref.status.numpy() == cells.status.numpy()
        a, b = cells.volume.double().numpy(), ref.volume.double().numpy()
        with np.errstate(invalid="ignore"):
            close = np.abs(a - b) <= CELL_RTOL[case.dtype] * np.abs(b)
        close |= np.isnan(a) & np.isnan(b)
        bad = np.nonzero(~(same & close))[0]
        if len(bad):
            self.report.add(case.kind, "silently_wrong", len(bad))
            i = int(bad[0])
            self.problem(case, impl, "silently_wrong",
                         f"{len(bad)} cells differ from the CPU's: cell {i} status {int(cells.status[i])} "
                         f"vs CPU {int(ref.status[i])}, volume {a[i]!r} vs CPU {b[i]!r}; cells {bad[:10].tolist()}",
                         cell=i, count=len(bad))


def _status_name(code: int) -> str:
    try:
        return CellStatus(int(code)).name
    except ValueError:
        return f"code {int(code)}"


def run_campaign(seed=0, cases: Sequence[int] = range(100), **kwargs) -> Report:
    """Runs the cases `cases` of campaign `seed` (Campaign's keywords) and returns the Report."""
    return Campaign(seed, **kwargs).run(cases)


def summary(report: Report) -> str:
    """The counts, per kind, the oracle's skip reasons and the problems, as text."""
    lines = ["", "fuzz summary: " + ", ".join(f"{k} {v}" for k, v in report.counts.items())
             + f" [{report.seconds:.1f} s]"]
    width = max([len(k) for k in report.per_kind] + [4])
    lines.append(f"  {'kind':<{width}} " + " ".join(f"{c[:14]:>14}" for c in COUNTERS))
    for kind, counts in sorted(report.per_kind.items()):
        lines.append(f"  {kind:<{width}} " + " ".join(f"{counts[c]:>14}" for c in COUNTERS))
    for reason, count in sorted(report.skip_reasons.items(), key=lambda kv: -kv[1]):
        lines.append(f"  oracle skipped {count} x: {reason}")
    for note, count in sorted(report.oracle_notes.items(), key=lambda kv: -kv[1]):
        lines.append(f"  oracle: {count} x {note}")
    if report.phase_seconds:
        lines.append("  seconds by phase: " + ", ".join(f"{name} {value:.0f}" for name, value in
                                                         sorted(report.phase_seconds.items(), key=lambda kv: -kv[1])))
        lines.append("  seconds by kind: " + ", ".join(f"{name} {value:.0f}" for name, value in
                                                        sorted(report.kind_seconds.items(), key=lambda kv: -kv[1])))
    for entry in report.slowest:
        lines.append(f"  slowest: {entry['seconds']:.1f} s {entry['case']}\n      replay: {entry['replay']}")
    for p in report.problems:
        lines.append(f"  [{p.category}] case {p.case} ({p.kind}, {p.dtype}, {p.device}, cells={p.cells_impl}): "
                     f"{p.message}\n      replay: {p.replay}")
    lines.append("fuzz: OK" if report.ok() else "fuzz: FAILED")
    return "\n".join(lines)


def merge_reports(reports: Sequence[Dict]) -> Report:
    """One Report from the as_dict() of several (the workers' shares of a campaign)."""
    merged = Report(settings=reports[0]["settings"])
    for part in reports:
        for name, value in part["counts"].items():
            merged.counts[name] += value
        for kind, counts in part["per_kind"].items():
            mine = merged.per_kind.setdefault(kind, dict.fromkeys(COUNTERS, 0))
            for name, value in counts.items():
                mine[name] += value
        for ours, theirs in ((merged.skip_reasons, part["oracle_skip_reasons"]),
                             (merged.oracle_notes, part["oracle_notes"])):
            for key, value in theirs.items():
                ours[key] = ours.get(key, 0) + value
        merged.slowest += part["slowest"]
        for ours, theirs in ((merged.phase_seconds, part.get("phase_seconds", {})),
                             (merged.kind_seconds, part.get("kind_seconds", {}))):
            for key, value in theirs.items():
                ours[key] = ours.get(key, 0.0) + value
        merged.problems += [Problem(**p) for p in part["problems"]]
        merged.seconds = max(merged.seconds, part["seconds"])
    merged.slowest = sorted(merged.slowest, key=lambda entry: -entry["seconds"])[:SLOWEST_CASES]
    merged.problems.sort(key=lambda p: p.case)
    return merged


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", type=int, default=100, help="run N cases (default 100) from --start")
    parser.add_argument("--start", type=int, default=0, help="index of the first case (default 0)")
    parser.add_argument("--case", type=int, action="append", help="run only this case (repeatable): replay")
    parser.add_argument("--seed", type=int, default=0, help="campaign seed")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"])
    parser.add_argument("--max-n", type=int, default=20000, help="largest number of points of a case")
    parser.add_argument("--dtype", default="both", choices=["float32", "float64", "both"])
    parser.add_argument("--cells", default="default", choices=["default", "thread", "cooperative", "all"],
                        help="cell implementation (TORCHVOR_CELLS); all: every case under thread and cooperative")
    parser.add_argument("--sample", type=int, default=12, help="cells a run checks against the oracle")
    parser.add_argument("--suspects", type=int, default=4,
                        help="float32 runs: also check the cells farthest from torchvor's float64 cells")
    parser.add_argument("--kinds", help="comma-separated subset of: " + ", ".join(KINDS))
    parser.add_argument("--compare-max-n", type=int, default=20000,
                        help="on CUDA, compare with the CPU for cases of at most this many points")
    parser.add_argument("--graph-max-n", type=int, default=20000,
                        help="also check voronoi_graph on cases of at most this many points (0: never)")
    parser.add_argument("--json", help="write the counts and problems to this file")
    parser.add_argument("--quiet", action="store_true", help="no line per case")
    parser.add_argument("--time-budget", type=float, default=0.0,
                        help="start no case after this many seconds (0: no budget); the summary counts the cases run")
    parser.add_argument("--case-timeout", type=float, default=600.0,
                        help="stop the campaign, counting a timeout, when a case runs longer (seconds; 0: never)")
    parser.add_argument("--workers", type=int, default=1,
                        help="run the cases in this many processes (each claims the next case when free), one report")
    parser.add_argument("--grace", type=float, default=60.0,
                        help="--workers with --time-budget: stop a worker this long past the budget (seconds)")
    parser.add_argument("--worker", type=int, default=None, help=argparse.SUPPRESS)  # this process's number
    parser.add_argument("--claim", default=None, help=argparse.SUPPRESS)  # the workers' counter (ClaimedCases)
    args = parser.parse_args(argv)
    if args.workers > 1 and args.worker is None:
        return run_workers(args, sys.argv[1:] if argv is None else list(argv), merge_reports, summary)
    kinds = [k.strip() for k in args.kinds.split(",")] if args.kinds else None
    for k in kinds or []:
        if k not in KINDS:
            parser.error(f"unknown kind {k!r}")
    if args.device == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available")
    campaign = Campaign(args.seed, device=args.device, max_n=args.max_n, dtype=args.dtype, cells=args.cells,
                        sample=args.sample, suspects=args.suspects, kinds=kinds, compare_max_n=args.compare_max_n,
                        graph_max_n=args.graph_max_n,
                        out=None if args.quiet else sys.stdout)
    indices = args.case if args.case is not None else range(args.start, args.start + args.cases)
    if args.claim is not None:
        indices = ClaimedCases(indices, args.claim)

    def finish():
        print(summary(campaign.report), flush=True)
        if args.json:
            with open(args.json, "w") as f:
                json.dump(campaign.report.as_dict(), f, indent=1, default=str)

    if args.case_timeout > 0:
        campaign.watch(args.case_timeout, lambda: (finish(), os._exit(1)))
    def save(report):  # a worker's report as of its last finished case (run_workers may stop it)
        with open(args.json + ".part", "w") as f:
            json.dump(report.as_dict(), f, default=str)
        os.replace(args.json + ".part", args.json)

    report = campaign.run(indices, time_budget=args.time_budget,
                          after_case=save if args.worker is not None and args.json else None)
    finish()
    return 0 if report.ok() else 1


if __name__ == "__main__":
    sys.exit(main())
