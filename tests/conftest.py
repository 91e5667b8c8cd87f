"""Shared fixtures for torchvor's tests.

* ``device``: every test runs on "cpu", and also on "cuda" when available.
* ``dtype``: float32 / float64 where a test asks for it.
* ``seed`` / ``gen``: fresh random inputs per test. The seed is drawn from the OS
  (or fixed with TORCHVOR_TEST_SEED=<int>) and printed in the report of a
  failing test, so a failure can be replayed.
* ``cells_impl`` / ``vertex_balls``: the Voronoi tests that take them run under
  each setting of TORCHVOR_CELLS / TORCHVOR_VERTEX_BALLS_K.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest
import torch

sys.path.insert(0, os.path.dirname(__file__))  # `import oracles`, `import voronoi_checks` from the tests
# A fresh cache for torch.compile's tests: inductor's cached code does not
# follow a change of an op's schema or fake kernel (a cached graph read the
# output of an older voronoi_graph).
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", tempfile.mkdtemp(prefix="torchvor_inductor_"))

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


@pytest.fixture(params=DEVICES)
def device(request):
    return torch.device(request.param)


@pytest.fixture(params=[torch.float32, torch.float64], ids=["float32", "float64"])
def dtype(request):
    return request.param


@pytest.fixture
def seed(request):
    fixed = os.environ.get("TORCHVOR_TEST_SEED")
    value = int(fixed) if fixed is not None else int.from_bytes(os.urandom(4), "little")
    request.node.user_properties.append(("seed", value))
    return value


@pytest.fixture
def gen(seed):
    """A CPU torch.Generator seeded per test (draw on CPU, then move: identical
    inputs on every device)."""
    g = torch.Generator()
    g.manual_seed(seed)
    return g


@pytest.fixture(params=["thread", "cooperative"])
def cells_impl(request, monkeypatch):
    """Which implementation clips the cells (TORCHVOR_CELLS): one thread per
    cell (ConvexCell, the CPU's default) or a group of lanes per cell
    (CooperativeCell: a warp on CUDA, its default; one lane on the CPU). The
    tests that take this fixture run both on every device."""
    monkeypatch.setenv("TORCHVOR_CELLS", request.param)
    return request.param


@pytest.fixture(params=["past 256", "every retry"])
def vertex_balls(request, monkeypatch):
    """The most neighbours a retry asks for (TORCHVOR_VERTEX_BALLS_K): cells
    that need more are finished on the grid by the empty balls of their
    vertices, from a list of that many. By default 256; with 1, every cell a
    retry takes is finished so, from its nearest neighbour alone. The tests
    that take this fixture run both."""
    if request.param == "every retry":
        monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", "1")
    return request.param


@pytest.fixture(scope="session")
def cpp_program(tmp_path_factory):
    """Builds tests/NAME.cpp against csrc/ (the core headers) and returns the
    executable's path: cpp_program("lane_emulation", "-pthread"). Skips
    without a C++ compiler."""
    compiler = os.environ.get("CXX") or shutil.which("c++") or shutil.which("g++")
    if compiler is None:
        pytest.skip("no C++ compiler")
    root = Path(__file__).resolve().parent.parent

    def build(name: str, *flags: str) -> Path:
        binary = tmp_path_factory.mktemp(name) / name
        done = subprocess.run([compiler, "-std=c++17", "-O1", *flags, f"-I{root / 'csrc'}",
                               str(root / "tests" / f"{name}.cpp"), "-o", str(binary)],
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr[-4000:]
        return binary

    return build


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.when == "call" and report.failed:
        for name, value in item.user_properties:
            if name == "seed":
                report.sections.append(
                    ("torchvor seed", f"replay with TORCHVOR_TEST_SEED={value} pytest '{item.nodeid}'"))


def pytest_addoption(parser):
    parser.addoption("--shard", default=None, metavar="I/N",
                     help="run only the I-th of N interleaved shares of the selected tests (0 <= I < N), "
                          "so N processes (one a GPU) run a selection between them")


@pytest.hookimpl(trylast=True)  # after -k and -m have deselected theirs
def pytest_collection_modifyitems(config, items):
    shard = config.getoption("shard")
    if not shard:
        return
    index, count = (int(part) for part in shard.split("/"))
    if not 0 <= index < count:
        raise pytest.UsageError(f"--shard {shard}: want I/N with 0 <= I < N")
    kept = [item for position, item in enumerate(items) if position % count == index]
    config.hook.pytest_deselected(items=[item for position, item in enumerate(items) if position % count != index])
    items[:] = kept
