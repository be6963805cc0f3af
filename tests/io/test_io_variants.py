"""Format variants found in the wild: headers, delimiters, meshes, organised and packed-colour PCDs."""

from __future__ import annotations

import numpy as np
import pytest

from minegeo.errors import FileFormatError
from minegeo.io import PointCloud, read_point_cloud, write_point_cloud


def test_cloudcompare_header_and_semicolons(tmp_path):
    p = tmp_path / "cc.txt"
    p.write_text("//X Y Z R G B\n1.5 2 3 255 0 10\n4 5 6 1 2 3\n")
    c = read_point_cloud(p)
    np.testing.assert_array_equal(c.points, [[1.5, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(c.attributes["rgb"], [[255, 0, 10], [1, 2, 3]])
    q = tmp_path / "semi.xyz"
    q.write_text("x;y;z;Intensity\n1;2;3;0.5\n4;5;6;0.25\n")
    c = read_point_cloud(q)
    np.testing.assert_array_equal(c.attributes["Intensity"], [0.5, 0.25])


def test_headerless_columns_are_not_guessed(tmp_path):
    p = tmp_path / "six.xyz"
    p.write_text("1 2 3 0.1 0.2 0.3\n4 5 6 0.4 0.5 0.6\n")
    c = read_point_cloud(p)
    assert sorted(c.attributes) == ["col4", "col5", "col6"] and c.normals is None
    c = read_point_cloud(p, columns=["x", "y", "z", "nx", "ny", "nz"])
    np.testing.assert_array_equal(c.normals, [[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]])


def test_ply_mesh_faces_are_skipped(tmp_path):
    head = "ply\nformat {fmt} 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
    p = tmp_path / "mesh_ascii.ply"
    p.write_text(head.format(fmt="ascii") + "0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n")
    c = read_point_cloud(p)
    assert len(c) == 3 and c.metadata["skipped_elements"] == ["face(1)"]
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype="<f8").tobytes()
    face = bytes([3]) + np.array([0, 1, 2], dtype="<i4").tobytes()
    q = tmp_path / "mesh_bin.ply"
    q.write_bytes(head.format(fmt="binary_little_endian").encode() + v + face)
    np.testing.assert_array_equal(read_point_cloud(q).points, c.points)


def test_ply_fixed_element_before_vertex_and_list_before_vertex(tmp_path):
    head = "ply\nformat binary_little_endian 1.0\nelement camera 1\nproperty float view_px\nproperty float view_py\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    body = np.array([9, 9], dtype="<f4").tobytes() + np.array([[1, 2, 3], [4, 5, 6]], dtype="<f4").tobytes()
    p = tmp_path / "cam.ply"
    p.write_bytes(head.encode() + body)
    np.testing.assert_array_equal(read_point_cloud(p).points, [[1, 2, 3], [4, 5, 6]])
    bad = head.replace("property float view_py", "property list uchar int idx")
    q = tmp_path / "listfirst.ply"
    q.write_bytes(bad.encode() + body)
    with pytest.raises(FileFormatError, match="list element 'camera' before the vertices"):
        read_point_cloud(q)


def test_pcd_organised_packed_rgba_and_padding(tmp_path):
    # 2 x 2 organised cloud, PCL-style padding field "_" and packed rgba (U 4)
    dt = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "<f4"), ("rgba", "<u4")])
    a = np.zeros(4, dt)
    a["x"] = [1, 2, np.nan, 4]
    a["y"] = [1, 2, np.nan, 4]
    a["z"] = [1, 2, np.nan, 4]
    a["rgba"] = [0x80FF0000, 0x8000FF00, 0, 0xFF0000FF]
    head = "VERSION 0.7\nFIELDS x y z _ rgba\nSIZE 4 4 4 4 4\nTYPE F F F F U\nCOUNT 1 1 1 1 1\nWIDTH 2\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA binary\n"
    p = tmp_path / "org.pcd"
    p.write_bytes(head.encode() + a.tobytes())
    with pytest.raises(FileFormatError, match="point 2"):
        read_point_cloud(p)
    c = read_point_cloud(p, drop_nonfinite=True)
    assert c.metadata["width"] == 2 and c.metadata["height"] == 2
    np.testing.assert_array_equal(c.attributes["rgb"], [[255, 0, 0], [0, 255, 0], [0, 0, 255]])
    np.testing.assert_array_equal(c.attributes["alpha"], [128, 128, 255])
    assert "_" not in c.attributes and not any(k.startswith("__pad") for k in c.attributes)


def test_pcd_pcl_float_rgb_ascii(tmp_path):
    packed = np.array([0x00FF8000, 0x000A0B0C], dtype=np.uint32)
    as_float = packed.view(np.float32)
    lines = "".join(f"{i} {i} {i} {v:.9g}\n" for i, v in enumerate(as_float))
    p = tmp_path / "rgb.pcd"
    p.write_text("VERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n" + lines)
    c = read_point_cloud(p)
    np.testing.assert_array_equal(c.attributes["rgb"], [[255, 128, 0], [10, 11, 12]])


def test_pcd_v5_without_count_and_comment_lines(tmp_path):
    p = tmp_path / "old.pcd"
    p.write_text("# .PCD v.5\n# a comment\nVERSION .5\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nWIDTH 2\nHEIGHT 1\nPOINTS 2\nDATA ascii\n1 2 3\n4 5 6\n")
    assert len(read_point_cloud(p)) == 2


def test_attribute_dtypes_preserved_binary(tmp_path, rng):
    attrs = {
        "i8": rng.integers(-128, 127, 10).astype(np.int8),
        "u16": rng.integers(0, 65535, 10).astype(np.uint16),
        "i32": rng.integers(-(2**31), 2**31 - 1, 10).astype(np.int32),
        "u32": rng.integers(0, 2**32 - 1, 10).astype(np.uint32),
        "f32": rng.random(10).astype(np.float32),
        "flag": rng.random(10) > 0.5,
    }
    c = PointCloud(rng.normal(size=(10, 3)), attributes=attrs)
    for name in ("a.ply", "a.pcd"):
        write_point_cloud(tmp_path / name, c)
        back = read_point_cloud(tmp_path / name)
        for k, v in attrs.items():
            np.testing.assert_array_equal(back.attributes[k], v)
            assert back.attributes[k].dtype == (np.uint8 if k == "flag" else v.dtype), (name, k)


def test_pts_and_3d_drop_what_they_cannot_store(tmp_path, rng, caplog):
    c = PointCloud(rng.normal(size=(5, 3)), normals=np.tile([0.0, 0, 1], (5, 1)), attributes={"label": np.arange(5)})
    write_point_cloud(tmp_path / "a.3d", c)
    assert "cannot store" in caplog.text
    assert sorted(read_point_cloud(tmp_path / "a.3d").attributes) == []


def test_float_colours_zero_to_one(tmp_path):
    head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nproperty float red\nproperty float green\nproperty float blue\nend_header\n"
    p = tmp_path / "fc.ply"
    p.write_text(head + "0 0 0 1 0 0.5\n1 1 1 0 1 1\n")
    c = read_point_cloud(p)
    np.testing.assert_array_equal(c.attributes["rgb"], [[255, 0, 128], [0, 255, 255]])
    assert c.metadata["rgb_source"].startswith("float 0..1")
