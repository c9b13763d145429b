"""The small PLY point reader: ascii and binary, both byte orders, extra properties and elements."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pidg  # noqa: F401
from pidg.data import DatasetError, read_ply_points, write_ply_points

XYZ = np.array([[0.0, 1.0, 2.0], [-1.5, 0.25, 3.0], [1e3, -2e-3, 0.5]], np.float32)
RGB = np.array([[0, 128, 255], [10, 20, 30], [255, 255, 255]], np.float64) / 255.0


@pytest.mark.parametrize("binary", [True, False])
def test_roundtrip(tmp_path, binary):
    path = tmp_path / "p.ply"
    write_ply_points(path, XYZ, RGB, binary=binary)
    cloud = read_ply_points(path)
    assert cloud.xyz.dtype == torch.float32 and len(cloud) == 3
    torch.testing.assert_close(cloud.xyz, torch.from_numpy(XYZ))
    torch.testing.assert_close(cloud.rgb, torch.from_numpy(RGB.astype(np.float32)))
    write_ply_points(path, XYZ, None, binary=binary)
    assert read_ply_points(path).rgb is None


def test_big_endian_doubles_normals_and_faces(tmp_path):
    """3DGS-style vertex layout (normals between xyz and colour), float64, big-endian, then a face element."""
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment made by hand\nelement vertex 3\n"
        "property double x\nproperty double y\nproperty double z\n"
        "property float nx\nproperty float ny\nproperty float nz\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\n"
        "element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    dtype = np.dtype(
        [
            ("x", ">f8"),
            ("y", ">f8"),
            ("z", ">f8"),
            ("nx", ">f4"),
            ("ny", ">f4"),
            ("nz", ">f4"),
            ("red", "u1"),
            ("green", "u1"),
            ("blue", "u1"),
        ]
    )
    table = np.zeros(3, dtype)
    table["x"], table["y"], table["z"] = XYZ.T
    table["red"], table["green"], table["blue"] = np.rint(RGB * 255).T
    face = np.array([3], "u1").tobytes() + np.array([0, 1, 2], ">i4").tobytes()
    path = tmp_path / "be.ply"
    path.write_bytes(header.encode() + table.tobytes() + face)
    cloud = read_ply_points(path)
    torch.testing.assert_close(cloud.xyz, torch.from_numpy(XYZ))
    torch.testing.assert_close(cloud.rgb, torch.from_numpy(RGB.astype(np.float32)))


def test_ascii_with_an_element_before_the_vertices_and_float_colours(tmp_path):
    path = tmp_path / "a.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement camera 1\nproperty float fov\nelement vertex 2\n"
        "property float x\nproperty float y\nproperty float z\n"
        "property float red\nproperty float green\nproperty float blue\nend_header\n"
        "0.7\n1 2 3 0.5 0.25 1.0\n4 5 6 0 0 0\n"
    )
    cloud = read_ply_points(path)
    assert cloud.xyz.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert cloud.rgb.tolist() == [[0.5, 0.25, 1.0], [0, 0, 0]]


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"hello", "not a PLY file"),
        (b"ply\nformat binary_little_endian 1.0\nelement vertex 2\nproperty float x\n", "no 'end_header'"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
            r"lacks properties \['z'\]",
        ),
        (
            b"ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
            b"property float z\nend_header\n" + b"\0" * 12,
            "truncated",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n1 2 3\n",
            "ends after 1 of 2",
        ),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n1 nan 3\n",
            "NaN",
        ),
        (b"ply\nformat weird 1.0\nelement vertex 0\nend_header\n", "unknown PLY format"),
    ],
)
def test_bad_files(tmp_path, content, message):
    path = tmp_path / "bad.ply"
    path.write_bytes(content)
    with pytest.raises(DatasetError, match=message):
        read_ply_points(path)


def test_missing_file(tmp_path):
    with pytest.raises(DatasetError, match="cannot read point cloud"):
        read_ply_points(tmp_path / "none.ply")
