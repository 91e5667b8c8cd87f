"""The cooperative cell on 8, 16 and 32 lanes, on a CPU (tests/lane_emulation.cpp).

The library runs csrc/core/cooperative_cell.h on the 32 lanes of a warp on the
GPU and on a single lane on the CPU, so without a GPU its multi-lane logic
(ballots, ranks, rounds of slots) would go untested. The program emulates the
lanes with host threads and checks each cell against the thread cell.
"""
import os
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def lane_emulation(tmp_path_factory):
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        pytest.skip("no C++ compiler")
    binary = tmp_path_factory.mktemp("lane_emulation") / "lane_emulation"
    build = subprocess.run([compiler, "-std=c++17", "-O1", "-pthread", f"-I{ROOT / 'csrc'}",
                            str(ROOT / "tests" / "lane_emulation.cpp"), "-o", str(binary)],
                           capture_output=True, text=True, timeout=600)
    assert build.returncode == 0, build.stderr[-4000:]
    return binary


def test_cooperative_cell_on_emulated_lanes(lane_emulation, seed):
    """White noise at tiers 0 and 1 (with exact duplicates), clustered points,
    and k=6 (cells that run out of neighbours): on 8, 16 and 32 lanes every
    cell gets the thread cell's status and neighbour count, and its volume
    to 1e-4. Where the thread cell runs out of planes, the lanes may hold up
    to six more (they keep no box plane that does not bound the cell): they
    then match a thread cell of six more planes, or run out no sooner."""
    run = subprocess.run([str(lane_emulation), str(seed), "12"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
