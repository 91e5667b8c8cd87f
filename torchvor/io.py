"""Reading and writing 3D point files, and writing Voronoi cell tables.

Point formats, chosen by the file name's suffix (case-insensitive):

* ``.npy``: a NumPy (N, 3) array of any real dtype (no pickles).
* ``.xyz``, ``.txt``: one point per line, 3 columns separated by whitespace
  and/or commas; ``#`` starts a comment; blank lines are skipped.
* ``.ply``: vertex positions (properties x, y, z of any scalar PLY type) from
  ``ascii``, ``binary_little_endian`` or ``binary_big_endian`` files; other
  vertex properties and other elements (faces, ...) are ignored.

Readers return float NumPy arrays of shape (N, 3) with N >= 1 and finite
values, or raise :class:`PointFileError` (a ValueError) whose message names
the file and, where it can, the line. Missing or unreadable files raise it too.
"""
from __future__ import annotations

import os
import re
from typing import Dict, List, Optional, Sequence, Tuple

import numpy as np

POINT_SUFFIXES = (".npy", ".xyz", ".txt", ".ply")
CELL_SUFFIXES = (".npz", ".npy")

_TEXT_SEPARATOR = re.compile(r"[,\s]+")

# PLY scalar type names (both spellings of the spec) -> NumPy type codes without byte order.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_PLY_BYTE_ORDER = {"binary_little_endian": "<", "binary_big_endian": ">"}


class PointFileError(ValueError):
    """A point file is missing, unreadable, malformed or holds unusable values."""


def suffix(path: str) -> str:
    return os.path.splitext(path)[1].lower()


# ---- reading --------------------------------------------------------------------------


def read_points(path: str) -> np.ndarray:
    """Points of a .npy, .xyz, .txt or .ply file as an (N, 3) float array.

    float32 data stays float32; double and integer data become float64.

    Raises:
        PointFileError: unknown suffix, missing/unreadable file, malformed
            content, not 3 columns, no points, or NaN/infinite coordinates.
    """
    kind = suffix(path)
    readers = {".npy": _read_npy, ".xyz": _read_text, ".txt": _read_text, ".ply": _read_ply}
    if kind not in readers:
        raise PointFileError(f"{path}: unknown point file type {kind or '(no suffix)'!r}; "
                             f"use one of {', '.join(POINT_SUFFIXES)}")
    if not os.path.exists(path):
        raise PointFileError(f"{path}: no such file")
    if os.path.isdir(path):
        raise PointFileError(f"{path}: is a directory, not a point file")
    try:
        points = readers[kind](path)
    except OSError as error:
        raise PointFileError(f"{path}: cannot read: {error.strerror or error}") from None
    return _checked_points(path, points)


def _checked_points(path: str, points: np.ndarray) -> np.ndarray:
    if points.shape[0] == 0:
        raise PointFileError(f"{path}: contains no points")
    if points.dtype != np.float32:
        points = points.astype(np.float64)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise PointFileError(f"{path}: {int(bad.sum())} point(s) have NaN or infinite coordinates "
                             f"(first: point {first + 1} of {points.shape[0]})")
    return np.ascontiguousarray(points)


def _read_npy(path: str) -> np.ndarray:
    with open(path, "rb") as handle:
        magic = handle.read(6)
    # Without the magic string np.load would try to unpickle and complain about pickles.
    if magic != b"\x93NUMPY":
        raise PointFileError(f"{path}: not a .npy file (no NumPy header)")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, EOFError) as error:
        # numpy says "Cannot load file containing pickled data..." or
        # "...not a valid NumPy file"-style messages; keep the first line.
        reason = str(error).splitlines()[0] if str(error) else type(error).__name__
        raise PointFileError(f"{path}: not a readable .npy array ({reason})") from None
    if not isinstance(array, np.ndarray) or array.dtype.kind not in "fiu":
        raise PointFileError(f"{path}: expected a real-valued array, got dtype {getattr(array, 'dtype', '?')}")
    if array.ndim != 2 or array.shape[1] != 3:
        raise PointFileError(f"{path}: expected an (N, 3) array of x y z columns, got shape {array.shape}")
    return array


def _read_text(path: str) -> np.ndarray:
    with open(path, "rb") as handle:
        raw = handle.read()
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as error:
        line = raw[: error.start].count(b"\n") + 1
        raise PointFileError(f"{path}, line {line}: not a text file (undecodable bytes)") from None
    if "\x00" in text:
        raise PointFileError(f"{path}, line {text[:text.index(chr(0))].count(chr(10)) + 1}: "
                             "not a text file (NUL byte)")
    rows: List[Tuple[str, str, str]] = []
    line_numbers: List[int] = []
    for number, line in enumerate(text.splitlines(), start=1):
        fields = _text_fields(line)
        if not fields:
            continue
        if len(fields) != 3:
            raise PointFileError(f"{path}, line {number}: expected 3 columns (x y z), found {len(fields)}")
        rows.append(fields)  # type: ignore[arg-type]
        line_numbers.append(number)
    try:
        values = np.array(rows, dtype=np.float64).reshape(len(rows), 3)
    except ValueError:
        _raise_first_bad_number(path, rows, line_numbers)
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        raise PointFileError(f"{path}, line {line_numbers[int(np.flatnonzero(bad)[0])]}: "
                             "NaN or infinite coordinate")
    return values


def _raise_first_bad_number(path: str, rows, line_numbers) -> None:
    """Slow path of _read_text: find the field that numpy could not convert."""
    for fields, number in zip(rows, line_numbers):
        for field in fields:
            try:
                float(field)
            except ValueError:
                raise PointFileError(f"{path}, line {number}: {field[:40]!r} is not a number") from None
    raise PointFileError(f"{path}: cannot convert the coordinates to numbers")


def _text_fields(line: str) -> List[str]:
    content = line.split("#", 1)[0].strip()
    if not content:
        return []
    return [field for field in _TEXT_SEPARATOR.split(content) if field]


class _PlyElement:
    def __init__(self, name: str, count: int):
        self.name = name
        self.count = count
        self.properties: List[Tuple[str, str]] = []  # (name, numpy code) of scalar properties
        self.has_list = False


def _read_ply(path: str) -> np.ndarray:
    with open(path, "rb") as handle:
        data = handle.read()
    header_lines, body_start = _split_ply_header(path, data)
    format_name, elements = _parse_ply_header(path, header_lines)
    vertex_index = next((i for i, e in enumerate(elements) if e.name == "vertex"), None)
    if vertex_index is None:
        raise PointFileError(f"{path}: PLY header has no 'element vertex'")
    vertex = elements[vertex_index]
    names = [name for name, _ in vertex.properties]
    missing = [axis for axis in "xyz" if axis not in names]
    if missing:
        raise PointFileError(f"{path}: PLY vertex element lacks propert{'y' if len(missing) == 1 else 'ies'} "
                             f"{' '.join(missing)}")
    if vertex.has_list:
        raise PointFileError(f"{path}: PLY vertex element with list properties is not supported")
    if format_name == "ascii":
        return _read_ply_ascii(path, data[body_start:], elements, vertex_index)
    return _read_ply_binary(path, data[body_start:], elements, vertex_index, _PLY_BYTE_ORDER[format_name])


def _split_ply_header(path: str, data: bytes) -> Tuple[List[str], int]:
    if not data.startswith(b"ply"):
        raise PointFileError(f"{path}: not a PLY file (it does not start with 'ply')")
    match = re.search(rb"end_header[ \t]*\r?\n", data)
    if match is None:
        raise PointFileError(f"{path}: PLY header has no 'end_header' line")
    try:
        header = data[: match.start()].decode("ascii")
    except UnicodeDecodeError:
        raise PointFileError(f"{path}: PLY header is not ASCII text") from None
    return header.splitlines(), match.end()


def _parse_ply_header(path: str, lines: Sequence[str]) -> Tuple[str, List[_PlyElement]]:
    format_name: Optional[str] = None
    elements: List[_PlyElement] = []
    for number, line in enumerate(lines[1:], start=2):
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        where = f"{path}, header line {number}"
        if words[0] == "format":
            if len(words) != 3 or words[1] not in ("ascii", *_PLY_BYTE_ORDER):
                raise PointFileError(f"{where}: unsupported PLY format {' '.join(words[1:])!r}")
            format_name = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise PointFileError(f"{where}: malformed element line {line.strip()!r}")
            elements.append(_PlyElement(words[1], int(words[2])))
        elif words[0] == "property":
            if not elements:
                raise PointFileError(f"{where}: property before any element")
            _add_ply_property(where, elements[-1], words)
        else:
            raise PointFileError(f"{where}: unexpected PLY header line {line.strip()[:40]!r}")
    if format_name is None:
        raise PointFileError(f"{path}: PLY header has no 'format' line")
    return format_name, elements


def _add_ply_property(where: str, element: _PlyElement, words: List[str]) -> None:
    if len(words) == 5 and words[1] == "list":
        if words[2] not in _PLY_TYPES or words[3] not in _PLY_TYPES:
            raise PointFileError(f"{where}: unknown PLY type in {' '.join(words)!r}")
        element.has_list = True
        return
    if len(words) != 3 or words[1] not in _PLY_TYPES:
        raise PointFileError(f"{where}: malformed or unknown-type property {' '.join(words)!r}")
    element.properties.append((words[2], _PLY_TYPES[words[1]]))


def _xyz_columns(table: np.ndarray) -> np.ndarray:
    columns = [table[axis] for axis in "xyz"]
    dtype = np.float32 if all(c.dtype == np.float32 for c in columns) else np.float64
    return np.stack([c.astype(dtype) for c in columns], axis=1)


def _read_ply_binary(path: str, body: bytes, elements: List[_PlyElement], vertex_index: int,
                     byte_order: str) -> np.ndarray:
    offset = 0
    for element in elements[:vertex_index]:
        if element.has_list:
            raise PointFileError(f"{path}: binary PLY with a list element ({element.name!r}) before "
                                 "the vertices is not supported")
        offset += element.count * _ply_dtype(path, element, byte_order).itemsize
    vertex = elements[vertex_index]
    dtype = _ply_dtype(path, vertex, byte_order)
    needed = offset + vertex.count * dtype.itemsize
    if len(body) < needed:
        raise PointFileError(f"{path}: PLY file is truncated ({len(body)} data bytes, the header "
                             f"announces at least {needed})")
    table = np.frombuffer(body, dtype=dtype, count=vertex.count, offset=offset)
    return _xyz_columns(table)


def _ply_dtype(path: str, element: _PlyElement, byte_order: str) -> np.dtype:
    try:
        return np.dtype([(name, byte_order + code) for name, code in element.properties])
    except ValueError as error:  # e.g. a property name given twice
        raise PointFileError(f"{path}: PLY element {element.name!r}: {error}") from None


def _read_ply_ascii(path: str, body: bytes, elements: List[_PlyElement], vertex_index: int) -> np.ndarray:
    try:
        lines = body.decode("ascii").splitlines()
    except UnicodeDecodeError:
        raise PointFileError(f"{path}: ASCII PLY body holds non-ASCII bytes") from None
    lines = [line for line in lines if line.strip()]
    first = sum(element.count for element in elements[:vertex_index])  # one line per element entry
    vertex = elements[vertex_index]
    if len(lines) < first + vertex.count:
        raise PointFileError(f"{path}: PLY file is truncated ({len(lines)} data lines, the header "
                             f"announces at least {first + vertex.count})")
    # Positions of x, y and z among the vertex properties, in that order.
    names = [name for name, _ in vertex.properties]
    columns = [names.index(axis) for axis in "xyz"]
    table = np.empty((vertex.count, 3), dtype=np.float64)
    width = len(vertex.properties)
    for row in range(vertex.count):
        fields = lines[first + row].split()
        if len(fields) != width:
            raise PointFileError(f"{path}: PLY vertex {row + 1}: expected {width} values, found {len(fields)}")
        try:
            table[row] = [float(fields[i]) for i in columns]
        except ValueError:
            raise PointFileError(f"{path}: PLY vertex {row + 1}: not a number in {lines[first + row][:60]!r}") from None
    as_float32 = all(code == "f4" for name, code in vertex.properties if name in ("x", "y", "z"))
    return table.astype(np.float32) if as_float32 else table


# ---- writing --------------------------------------------------------------------------


def write_points(path: str, points, *, ply_format: str = "binary_little_endian") -> None:
    """Write (N, 3) points (NumPy array or tensor) by suffix: .npy, .xyz/.txt or .ply.

    PLY files get float (float32 input) or double vertex properties x y z,
    binary little-endian unless ``ply_format="ascii"``. Text files use
    ``repr``-exact precision (9 or 17 significant digits).

    Raises:
        ValueError: unknown suffix, bad shape or ply_format.
        OSError: the file cannot be written.
    """
    array = _as_numpy_points(points)
    kind = suffix(path)
    if kind == ".npy":
        with open(path, "wb") as handle:  # a handle: np.save(path) would append ".npy" to odd names
            np.save(handle, array)
    elif kind in (".xyz", ".txt"):
        digits = 9 if array.dtype == np.float32 else 17
        np.savetxt(path, array, fmt=f"%.{digits}g", header="x y z")
    elif kind == ".ply":
        _write_ply(path, array, ply_format)
    else:
        raise ValueError(f"{path}: unknown point file type {kind or '(no suffix)'!r}; "
                         f"use one of {', '.join(POINT_SUFFIXES)}")


def _as_numpy_points(points) -> np.ndarray:
    if hasattr(points, "detach"):
        points = points.detach().cpu().numpy()
    array = np.asarray(points)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"points must have shape (N, 3), got {array.shape}")
    if array.dtype not in (np.float32, np.float64):
        array = array.astype(np.float64)
    return np.ascontiguousarray(array)


def _write_ply(path: str, array: np.ndarray, ply_format: str) -> None:
    if ply_format not in ("ascii", "binary_little_endian"):
        raise ValueError(f"ply_format must be 'ascii' or 'binary_little_endian', got {ply_format!r}")
    type_name = "float" if array.dtype == np.float32 else "double"
    header = (f"ply\nformat {ply_format} 1.0\ncomment written by torchvor\n"
              f"element vertex {array.shape[0]}\n"
              f"property {type_name} x\nproperty {type_name} y\nproperty {type_name} z\nend_header\n")
    with open(path, "wb") as handle:
        handle.write(header.encode("ascii"))
        if ply_format == "ascii":
            digits = 9 if array.dtype == np.float32 else 17
            np.savetxt(handle, array, fmt=f"%.{digits}g")
        else:
            handle.write(array.astype(array.dtype.newbyteorder("<"), copy=False).tobytes())


def cell_table(points, cells) -> Dict[str, np.ndarray]:
    """NumPy arrays of points and :class:`~torchvor.VoronoiCells` fields, by name."""
    def numpy(tensor):
        return tensor.detach().cpu().numpy()

    return {
        "points": numpy(points), "volume": numpy(cells.volume), "centroid": numpy(cells.centroid),
        "second_moment": numpy(cells.second_moment), "status": numpy(cells.status),
        "neighbors_needed": numpy(cells.neighbors_needed),
    }


def write_cells(path: str, points, cells) -> None:
    """Write the cells of ``points`` by suffix.

    * ``.npz``: arrays ``points`` (N, 3), ``volume`` (N,), ``centroid`` (N, 3),
      ``second_moment`` (N,), ``status`` (N,) int8 (:class:`~torchvor.CellStatus`
      codes) and ``neighbors_needed`` (N,) int32 (nearest neighbours the cell needed).
    * ``.npy``: one structured array of N records with the same field names
      (``point`` instead of ``points``), e.g. ``table["volume"]``.

    Floating fields keep the points' dtype. Raises ValueError for another
    suffix, OSError when the file cannot be written.
    """
    table = cell_table(points, cells)
    kind = suffix(path)
    if kind == ".npz":
        with open(path, "wb") as handle:  # a handle: np.savez(path) would append ".npz" to odd names
            np.savez(handle, **table)
    elif kind == ".npy":
        real = table["volume"].dtype
        records = np.empty(table["volume"].shape[0], dtype=[
            ("point", real, (3,)), ("volume", real), ("centroid", real, (3,)),
            ("second_moment", real), ("status", np.int8), ("neighbors_needed", np.int32)])
        records["point"] = table["points"]
        for name in ("volume", "centroid", "second_moment", "status", "neighbors_needed"):
            records[name] = table[name]
        with open(path, "wb") as handle:
            np.save(handle, records)
    else:
        raise ValueError(f"{path}: unknown cell file type {kind or '(no suffix)'!r}; use .npz or .npy")


__all__ = ["PointFileError", "read_points", "write_points", "write_cells", "cell_table",
           "POINT_SUFFIXES", "CELL_SUFFIXES"]
