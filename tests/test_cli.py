"""`python -m torchvor` (subprocess) and the point-file readers/writers it uses."""
import os
import struct
import subprocess
import sys

import numpy as np
import pytest
import torch

from torchvor import io as point_io
from torchvor.lloyd import lloyd


# Points strictly inside their bounding box plus its corners, so the box read
# back equals the one the test computes.
POINTS = np.array([
    [0.0, 0.0, 0.0], [1.0, 2.0, 3.0], [0.25, 0.5, 0.75], [0.75, 1.5, 2.25],
    [0.5, 0.25, 1.0], [0.125, 1.75, 2.5], [0.875, 0.875, 0.5], [0.375, 1.25, 1.875],
])


def run_cli(*arguments, cwd=None):
    return subprocess.run([sys.executable, "-m", "torchvor", *map(str, arguments)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def assert_one_line_error(result, *fragments):
    assert result.returncode == 2, (result.stdout, result.stderr)
    assert "Traceback" not in result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("torchvor: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


# ---- hand-written inputs (independent of torchvor.io's writers) ------------------------


def write_text(path, points, separator=" "):
    rows = [separator.join(repr(float(v)) for v in row) for row in points]
    body = "# x y z\n\n" + "\n".join(rows[:2]) + "   # a comment\n" + "\n".join(rows[2:]) + "\n"
    path.write_text(body)


def write_ply_ascii(path, points):
    header = ("ply\nformat ascii 1.0\ncomment hand-written\nelement vertex {n}\n"
              "property double x\nproperty double y\nproperty double z\nproperty uchar red\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    rows = "".join(f"{x!r} {y!r} {z!r} 7\n" for x, y, z in points.tolist())
    path.write_text(header.format(n=len(points)) + rows + "3 0 1 2\n")


def write_ply_binary(path, points):
    # float32 z before double x y: property order and mixed types must not matter.
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(points)}\n"
              "property float z\nproperty double x\nproperty double y\nend_header\n").encode()
    body = b"".join(struct.pack("<fdd", z, x, y) for x, y, z in points.tolist())
    path.write_bytes(header + body)


WRITERS = {
    "npy": lambda path, points: np.save(path, points),
    "xyz": write_text,
    "txt": lambda path, points: write_text(path, points, separator=", "),
    "ascii.ply": write_ply_ascii,
    "binary.ply": write_ply_binary,
}


# ---- readers and writers, in process --------------------------------------------------


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_read_points_of_every_format(tmp_path, kind):
    path = tmp_path / f"points.{kind}"
    WRITERS[kind](path, POINTS)
    points = point_io.read_points(str(path))
    assert points.shape == (len(POINTS), 3)
    tolerance = 1e-7 if kind == "binary.ply" else 0  # z stored as float32 there
    np.testing.assert_allclose(points, POINTS, rtol=0, atol=tolerance)


@pytest.mark.parametrize("suffix", [".npy", ".xyz", ".txt", ".ply"])
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_write_then_read_is_exact(tmp_path, suffix, dtype):
    points = np.random.default_rng(0).random((50, 3)).astype(dtype)
    path = str(tmp_path / f"out{suffix}")
    point_io.write_points(path, torch.from_numpy(points))
    back = point_io.read_points(path)
    # Text carries no dtype (read as float64) but enough digits to restore it exactly.
    assert back.dtype == (np.float64 if suffix in (".xyz", ".txt") else dtype)
    np.testing.assert_array_equal(back.astype(dtype), points)


def test_ascii_ply_writer_and_big_endian_reader(tmp_path):
    path = str(tmp_path / "ascii.ply")
    point_io.write_points(path, POINTS, ply_format="ascii")
    np.testing.assert_array_equal(point_io.read_points(path), POINTS)
    big = tmp_path / "big.ply"
    big.write_bytes(f"ply\nformat binary_big_endian 1.0\nelement vertex {len(POINTS)}\nproperty double x\n"
                    "property double y\nproperty double z\nend_header\n".encode() + POINTS.astype(">f8").tobytes())
    np.testing.assert_array_equal(point_io.read_points(str(big)), POINTS)


BROKEN_FILES = {
    "garbage.npy": (os.urandom(64), "not a .npy file"),
    "garbage.ply": (b"\x00\xff" * 40, "not a PLY file"),
    "garbage.xyz": (b"\xff\xfe\x00\x01" * 20, "not a text file"),
    "columns.txt": (b"0 0 0\n1 1\n", "line 2: expected 3 columns"),
    "word.xyz": (b"0 0 0\n1 one 1\n", "'one' is not a number"),
    "nan.xyz": (b"0 0 0\n# ok\nnan 1 1\n", "line 3: NaN"),
    "empty.txt": (b"# nothing\n", "no points"),
    "truncated.ply": (b"ply\nformat binary_little_endian 1.0\nelement vertex 9\nproperty float x\n"
                      b"property float y\nproperty float z\nend_header\n" + b"\x00" * 20, "truncated"),
    "noz.ply": (b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\n"
                b"end_header\n0 0\n", "lacks property z"),
    "unknown.csv": (b"0 0 0\n", "unknown point file type"),
}


@pytest.mark.parametrize("name", sorted(BROKEN_FILES))
def test_read_points_rejects_broken_files(tmp_path, name):
    content, fragment = BROKEN_FILES[name]
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(point_io.PointFileError) as info:
        point_io.read_points(str(path))
    assert fragment in str(info.value) and "\n" not in str(info.value)


def test_npy_with_wrong_shape_or_nan_is_rejected(tmp_path):
    np.save(tmp_path / "wide.npy", np.zeros((4, 4)))
    with pytest.raises(point_io.PointFileError, match=r"\(N, 3\)"):
        point_io.read_points(str(tmp_path / "wide.npy"))
    np.save(tmp_path / "nan.npy", np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 1.0]]))
    with pytest.raises(point_io.PointFileError, match="NaN"):
        point_io.read_points(str(tmp_path / "nan.npy"))


# ---- the command line ------------------------------------------------------------------


@pytest.mark.parametrize("kind", sorted(WRITERS))
def test_cli_round_trips_every_format(tmp_path, kind):
    """0 iterations write back what was read; the output format follows --out."""
    source = tmp_path / f"in.{kind}"
    WRITERS[kind](source, POINTS)
    out = tmp_path / f"out{os.path.splitext(kind)[1] or '.' + kind}"
    result = run_cli("lloyd", source, "--iters", 0, "--dtype", "float64", "--out", out, "--device", "cpu")
    assert result.returncode == 0, result.stderr
    assert str(out) in result.stdout
    np.testing.assert_array_equal(point_io.read_points(str(out)), point_io.read_points(str(source)))


def test_cli_lloyd_matches_the_library(tmp_path, device):
    source = tmp_path / "in.npy"
    np.save(source, POINTS)
    out = tmp_path / "relaxed.ply"
    result = run_cli("lloyd", source, "--iters", 3, "--dtype", "float64", "--device", device.type, "--out", out)
    assert result.returncode == 0, result.stderr
    progress = [line for line in result.stderr.splitlines() if line.startswith("lloyd ")]
    assert len(progress) == 3 and "energy" in progress[0] and "displacement" in progress[0]
    expected = lloyd(torch.from_numpy(POINTS), iters=3).numpy()  # bounding box, as the CLI
    np.testing.assert_allclose(point_io.read_points(str(out)), expected, rtol=0, atol=1e-12)


def test_cli_generates_white_noise_and_respects_quiet_and_tol(tmp_path):
    out = tmp_path / "noise.npy"
    result = run_cli("lloyd", "--n", 500, "--iters", 50, "--tol", "0.5", "--seed", 3, "--quiet", "--out", out)
    assert result.returncode == 0, result.stderr
    assert result.stderr == ""
    points = np.load(out)
    assert points.shape == (500, 3) and points.dtype == np.float32
    assert ((points >= 0) & (points <= 1)).all()
    # tol 0.5 of the diagonal: the first iteration already moves less.
    from torchvor.samples import white_noise

    np.testing.assert_allclose(points, lloyd(white_noise(500, seed=3), ([0, 0, 0], [1, 1, 1]), iters=1).numpy(),
                               rtol=0, atol=1e-7)


@pytest.mark.parametrize("suffix", [".npz", ".npy"])
def test_cli_cells_writes_the_cell_table(tmp_path, suffix):
    out = tmp_path / f"cells{suffix}"
    result = run_cli("cells", "--n", 300, "--dtype", "float64", "--box", 0, 0, 0, 1, 1, 1, "--out", out)
    assert result.returncode == 0, result.stderr
    table = np.load(out)
    if suffix == ".npz":
        volume, status, neighbors = table["volume"], table["status"], table["neighbors_needed"]
        assert table["points"].shape == table["centroid"].shape == (300, 3)
    else:
        assert set(table.dtype.names) == {"point", "volume", "centroid", "second_moment", "status", "neighbors_needed"}
        volume, status, neighbors = table["volume"], table["status"], table["neighbors_needed"]
    assert volume.shape == (300,) and abs(volume.sum() - 1) < 1e-12
    assert (status == 0).all() and status.dtype == np.int8 and (neighbors > 0).all()


def test_cli_graph_writes_the_faces(tmp_path):
    """`graph` writes the library's Voronoi graph of the points."""
    import torchvor

    source = tmp_path / "points.npy"
    np.save(source, POINTS)
    out = tmp_path / "graph.npz"
    result = run_cli("graph", source, "--dtype", "float64", "--out", out)
    assert result.returncode == 0, result.stderr
    saved = np.load(out)
    expected = torchvor.voronoi_graph(torch.from_numpy(POINTS), (POINTS.min(0), POINTS.max(0)))
    np.testing.assert_array_equal(saved["edge_index"], expected.edge_index.numpy())
    np.testing.assert_allclose(saved["area"], expected.area.numpy(), rtol=1e-12)
    np.testing.assert_allclose(saved["centroid"], expected.centroid.numpy(), rtol=1e-12)
    np.testing.assert_allclose(saved["wall_area"], expected.wall_area.numpy(), rtol=1e-12)
    assert saved["points"].shape == (8, 3) and (saved["status"] == 0).all()
    assert_one_line_error(run_cli("graph", source, "--out", tmp_path / "graph.npy"), ".npz")


def test_cli_plot_writes_a_png(tmp_path):
    pytest.importorskip("matplotlib")
    picture = tmp_path / "lloyd.png"
    result = run_cli("lloyd", "--n", 300, "--iters", 3, "--out", tmp_path / "p.npy", "--plot", picture, "--quiet")
    assert result.returncode == 0, result.stderr
    assert str(picture) in result.stdout
    assert picture.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")


BROKEN_INPUTS = {
    "garbage.npy": (os.urandom(200), "not a .npy file"),
    "garbage.ply": (os.urandom(200), "not a PLY file"),
    "columns.xyz": (b"0 0 0\n1 1 1 1\n", "expected 3 columns"),
    "nan.txt": (b"0 0 0\n1 1 1\nnan 0.5 0.5\n", "NaN"),
}


@pytest.mark.parametrize("name", sorted(BROKEN_INPUTS))
def test_cli_broken_input_exits_2_with_one_line(tmp_path, name):
    content, fragment = BROKEN_INPUTS[name]
    (tmp_path / name).write_bytes(content)
    result = run_cli("lloyd", tmp_path / name, "--out", tmp_path / "o.npy")
    assert_one_line_error(result, name, fragment)


@pytest.mark.parametrize("arguments, fragment", [
    (["lloyd", "missing.npy", "--out", "o.npy"], "no such file"),
    (["cells", "in.npy", "--box", 0, 0, 0, 0.5, 5, 5, "--out", "c.npz"], "outside --box"),
    (["lloyd", "in.npy", "--out", "o.csv"], "must end with"),
    (["cells", "in.npy", "--out", "o.ply"], "must end with .npz, .npy"),
    (["lloyd", "in.npy", "--out", "no/such/dir/o.npy"], "does not exist"),
])
def test_cli_bad_arguments_exit_2_with_one_line(tmp_path, arguments, fragment):
    np.save(tmp_path / "in.npy", POINTS)
    result = run_cli(*arguments, cwd=tmp_path)
    assert_one_line_error(result, fragment)


def test_cli_usage_errors_come_from_argparse():
    result = run_cli("lloyd", "--iters", "-3", "--out", "o.npy")
    assert result.returncode == 2 and "Traceback" not in result.stderr and "--iters" in result.stderr


# ---- version, and --plot without matplotlib ---------------------------------------------


def test_cli_version():
    import torchvor

    result = run_cli("--version")
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == f"torchvor {torchvor.__version__} (torch {torch.__version__})"


def _main_without_matplotlib(*arguments, cwd):
    code = ("import sys; sys.modules['matplotlib'] = None\n"  # makes `import matplotlib` fail
            "from torchvor.cli import main\n"
            f"sys.exit(main({[str(a) for a in arguments]!r}))")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=cwd)


@pytest.mark.parametrize("arguments", [["lloyd", "--iters", 1, "--out", "p.npy"], ["cells", "--out", "c.npz"]],
                         ids=["lloyd", "cells"])
def test_cli_plot_without_matplotlib_writes_the_results_and_skips_the_picture(tmp_path, arguments):
    """matplotlib is optional: the results are written, the picture is skipped with a warning, exit 0."""
    result = _main_without_matplotlib(*arguments, "--n", 50, "--plot", "x.png", cwd=tmp_path)
    assert result.returncode == 0, result.stderr
    assert "Traceback" not in result.stderr
    assert (tmp_path / arguments[-1]).exists() and not (tmp_path / "x.png").exists()
    assert "wrote 50 " in result.stdout
    warning = [line for line in result.stderr.splitlines() if line.startswith("torchvor: warning: ")]
    assert len(warning) == 1 and "skipped the picture x.png" in warning[0], result.stderr
    assert "pip install matplotlib" in warning[0]


def test_cli_plot_without_matplotlib_still_checks_its_directory(tmp_path):
    result = _main_without_matplotlib("lloyd", "--n", 10, "--out", "p.npy", "--plot", "no/such/dir/x.png",
                                      cwd=tmp_path)
    assert_one_line_error(result, "--plot", "does not exist")
    assert not (tmp_path / "p.npy").exists()
