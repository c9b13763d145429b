"""A small PLY reader/writer for point clouds (vertex x, y, z and optional red, green, blue).

Enough for the initial clouds that ship with datasets (``points3d.ply`` of the PIDG scenes, the files 3DGS-style
code writes): ascii, binary little- and big-endian, any scalar property types, extra vertex properties such as
normals ignored, other elements (faces) skipped. Written here rather than depending on ``plyfile`` because
this is all the project needs from PLY.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pidg.data.scene import DatasetError, PointCloud

# PLY scalar type names (both spellings) -> numpy type codes without byte order.
_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip

_COLOR_NAMES = ("red", "green", "blue")


class _Element:
    def __init__(self, name: str, count: int) -> None:
        self.name = name
        self.count = count
        self.properties: list[tuple[str, str]] = []  # (name, numpy type code)
        self.has_list = False


def _parse_header(path: Path, data: bytes) -> tuple[str, list[_Element], int]:
    """Return (format, elements, byte offset of the body)."""
    if not data.startswith(b"ply"):
        raise DatasetError(path, "not a PLY file (it does not start with 'ply')")
    end = data.find(b"end_header")
    if end < 0:
        raise DatasetError(path, "PLY header has no 'end_header' line")
    body = data.index(b"\n", end) + 1 if b"\n" in data[end:] else len(data)
    fmt = ""
    elements: list[_Element] = []
    for raw in data[:end].decode("ascii", errors="replace").splitlines()[1:]:
        words = raw.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format" and len(words) >= 2:
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            count = int(words[2]) if words[2].isdigit() else -1  # a negative count would read "all" in numpy
            if count < 0:
                raise DatasetError(path, f"bad PLY element line {raw!r} (expected a name and a count >= 0)")
            elements.append(_Element(words[1], count))
        elif words[0] == "property" and elements:
            if words[1] == "list":
                elements[-1].has_list = True
                elements[-1].properties.append((words[-1], "list"))
            elif len(words) == 3 and words[1] in _PLY_TYPES:
                elements[-1].properties.append((words[2], _PLY_TYPES[words[1]]))
            else:
                raise DatasetError(path, f"unsupported PLY property line {raw!r}")
        else:
            raise DatasetError(path, f"unexpected PLY header line {raw!r}")
    if fmt not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise DatasetError(path, f"unknown PLY format {fmt!r}")
    return fmt, elements, body


def read_ply_points(path: Path | str) -> PointCloud:
    """Read vertex positions (and uchar or float colours, if present) from a PLY file.

    uchar colours are divided by 255; float colours are taken as already in [0, 1].
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as e:
        raise DatasetError(path, f"cannot read point cloud: {e.strerror or e}") from None
    fmt, elements, offset = _parse_header(path, data)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise DatasetError(path, "PLY file has no 'vertex' element")
    vertex = elements[names.index("vertex")]
    props = dict(vertex.properties)
    missing = [p for p in ("x", "y", "z") if p not in props]
    if missing:
        raise DatasetError(path, f"PLY vertex element lacks properties {missing}")
    if vertex.has_list:
        raise DatasetError(path, "PLY vertex element with list properties is not supported")
    if vertex.count == 0:
        raise DatasetError(path, _EMPTY)

    if fmt == "ascii":
        table = _read_ascii_vertices(path, data[offset:], elements, vertex)
    else:
        table = _read_binary_vertices(
            path, data, offset, elements, vertex, "<" if fmt.endswith("little_endian") else ">"
        )

    xyz = np.stack([np.asarray(table["x"], np.float64), np.asarray(table["y"]), np.asarray(table["z"])], axis=1)
    check_points(path, xyz)
    rgb = None
    if all(c in props for c in _COLOR_NAMES):
        cols = np.stack([np.asarray(table[c], np.float64) for c in _COLOR_NAMES], axis=1)
        _check_finite(path, cols, "colours")
        if props["red"] in ("u1",):
            cols = cols / 255.0
        elif props["red"] in ("u2",):
            cols = cols / 65535.0
        rgb = torch.from_numpy(np.clip(cols, 0.0, 1.0).astype(np.float32))
    return PointCloud(torch.from_numpy(xyz.astype(np.float32)), rgb)


#: Largest accepted |coordinate| of an initial point, in scene units. Scenes are a few units across (D-NeRF
#: cameras sit ~4 from the origin) and even far outliers of a real capture's cloud stay orders of magnitude below
#: this, while float32 resolves only 0.06 units at 1e6: beyond it a value is garbage (1e30 from uninitialised
#: memory, a float64 that would overflow float32) or a unit mix-up, not geometry.
MAX_POINT_COORDINATE = 1e6
_EMPTY = "point cloud has 0 points; remove the file to initialise without it"


def check_points(path: Path, xyz: np.ndarray) -> None:
    """Reject an empty cloud, NaN/infinite and absurdly large coordinates here, where the file can be named;
    later they would surface as a bad scene box or a failed initialisation far from their cause."""
    if len(xyz) == 0:
        raise DatasetError(path, _EMPTY)
    _check_finite(path, xyz, "coordinates")
    far = np.abs(xyz).max(axis=1) > MAX_POINT_COORDINATE
    if far.any():
        first = int(np.argmax(far))
        raise DatasetError(
            path,
            f"{int(far.sum())} of {len(xyz)} points have coordinates beyond +-{MAX_POINT_COORDINATE:g} scene units "
            f"(point {first} is ({', '.join(f'{v:.6g}' for v in xyz[first])}))",
        )


def _check_finite(path: Path, values: np.ndarray, what: str) -> None:
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        raise DatasetError(
            path, f"{int(bad.sum())} of {len(values)} points have NaN or infinite {what} (first: point {first})"
        )


def _read_ascii_vertices(path: Path, body: bytes, elements: list[_Element], vertex: _Element) -> dict[str, np.ndarray]:
    lines = body.decode("ascii", errors="replace").splitlines()
    # In ascii PLY every element instance is one line, so earlier elements are skipped by counting lines.
    start = 0
    for e in elements:
        if e is vertex:
            break
        start += e.count
    rows = lines[start : start + vertex.count]
    if len(rows) < vertex.count:
        raise DatasetError(path, f"PLY file ends after {len(rows)} of {vertex.count} vertices")
    try:
        values = np.array([r.split()[: len(vertex.properties)] for r in rows], dtype=np.float64)
    except ValueError:
        raise DatasetError(
            path, "PLY ascii vertex rows are malformed (wrong number of values or not numbers)"
        ) from None
    if values.shape != (vertex.count, len(vertex.properties)):
        raise DatasetError(path, "PLY ascii vertex rows have the wrong number of values")
    return {name: values[:, i] for i, (name, _) in enumerate(vertex.properties)}


def _read_binary_vertices(
    path: Path, data: bytes, offset: int, elements: list[_Element], vertex: _Element, order: str
) -> np.ndarray:
    for e in elements:
        if e is vertex:
            break
        if e.has_list:  # variable-size records: would need a full parse to skip
            raise DatasetError(path, f"PLY element {e.name!r} with list properties before 'vertex' is not supported")
        offset += e.count * sum(np.dtype(t).itemsize for _, t in e.properties)
    dtype = np.dtype([(name, order + t) for name, t in vertex.properties])
    if len(data) < offset + vertex.count * dtype.itemsize:
        raise DatasetError(path, f"PLY file is truncated: {vertex.count} vertices of {dtype.itemsize} bytes do not fit")
    return np.frombuffer(data, dtype=dtype, count=vertex.count, offset=offset)


def write_ply_points(
    path: Path | str, xyz: np.ndarray | torch.Tensor, rgb: np.ndarray | torch.Tensor | None = None, binary: bool = True
) -> None:
    """Write points [P, 3] (and colours [P, 3] in [0, 1], stored as uchar) as a PLY file."""
    xyz = np.asarray(xyz, dtype=np.float32).reshape(-1, 3)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if rgb is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    table = np.empty(len(xyz), dtype=fields)
    table["x"], table["y"], table["z"] = xyz.T
    if rgb is not None:
        cols = np.clip(np.rint(np.asarray(rgb, dtype=np.float64).reshape(-1, 3) * 255.0), 0, 255).astype(np.uint8)
        table["red"], table["green"], table["blue"] = cols.T
    header = ["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0", f"element vertex {len(xyz)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in fields] + ["end_header"]
    with open(path, "wb") as f:
        f.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            f.write(table.tobytes())
        else:
            for row in table:
                f.write((" ".join(repr(float(v)) if i < 3 else str(int(v)) for i, v in enumerate(row)) + "\n").encode())
