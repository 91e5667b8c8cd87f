"""The cooperative cell on 8, 16 and 32 lanes, on a CPU (tests/lane_emulation.cpp).

The library runs csrc/core/cooperative_cell.h on the 32 lanes of a warp on the
GPU and on a single lane on the CPU, so without a GPU its multi-lane logic
(ballots, ranks, rounds of slots) would go untested. The program emulates the
lanes with host threads and checks each cell against the thread cell.
"""
import subprocess

import pytest


@pytest.fixture(scope="module")
def lane_emulation(cpp_program):
    return cpp_program("lane_emulation", "-pthread")


def test_cooperative_cell_on_emulated_lanes(lane_emulation, seed):
    """White noise at tiers 0 and 1 (with exact duplicates), clustered points,
    and k=6 (cells that run out of neighbours): on 8, 16 and 32 lanes every
    cell gets the thread cell's status and neighbour count, and its volume
    to 1e-4. Where the thread cell runs out of planes, the lanes may hold up
    to six more (they keep no box plane that does not bound the cell): they
    then match a thread cell of six more planes, or run out no sooner."""
    run = subprocess.run([str(lane_emulation), str(seed), "12"], capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
