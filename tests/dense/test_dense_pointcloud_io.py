"""LAS/LAZ and PLY point clouds: round trips at UTM coordinates, foreign readers, malformed files."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.errors import InputError
from oblique_city.core.io.pointcloud import PointCloud, read_las, read_ply, write_las, write_ply


@pytest.fixture
def cloud() -> PointCloud:
    rng = np.random.default_rng(0)
    n = 2000
    normal = rng.normal(size=(n, 3))
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return PointCloud(rng.uniform(0, 200, (n, 3)) + [500000.0, 5400000.0, 100.0], rng.integers(0, 256, (n, 3)),
                      normal, rng.integers(0, 5, n), rng.integers(0, 12, n), [f"m{i}" for i in range(12)],
                      "EPSG:32632")


@pytest.mark.parametrize("suffix", [".las", ".laz"])
def test_las_round_trip(tmp_path, cloud, suffix):
    path = tmp_path / ("points" + suffix)
    write_las(path, cloud)
    back = read_las(path)
    assert np.abs(back.xyz - cloud.xyz).max() <= 0.0005 + 1e-9  # 1 mm scale
    assert (back.rgb == cloud.rgb).all() and (back.view == cloud.view).all() and (back.master == cloud.master).all()
    assert np.abs(back.normal - cloud.normal).max() < 1e-6
    assert "UTM zone 32N" in back.crs


def test_laz_is_compressed(tmp_path, cloud):
    write_las(tmp_path / "a.las", cloud)
    write_las(tmp_path / "a.laz", cloud)
    assert (tmp_path / "a.laz").stat().st_size < 0.8 * (tmp_path / "a.las").stat().st_size


def test_ply_round_trip_and_open3d_reads_it(tmp_path, cloud):
    import open3d as o3d

    path = tmp_path / "points.ply"
    write_ply(path, cloud)
    back = read_ply(path)
    assert np.array_equal(back.xyz, cloud.xyz)  # doubles: UTM coordinates keep every digit
    assert (back.rgb == cloud.rgb).all() and (back.master == cloud.master).all() and (back.view == cloud.view).all()
    assert back.masters == cloud.masters and back.crs == "EPSG:32632"
    pcd = o3d.io.read_point_cloud(str(path))
    assert len(pcd.points) == len(cloud) and pcd.has_colors() and pcd.has_normals()
    assert np.allclose(np.asarray(pcd.colors) * 255, cloud.rgb, atol=0.5)


def test_ply_errors(tmp_path):
    p = tmp_path / "bad.ply"
    p.write_bytes(b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with pytest.raises(InputError, match="binary_little_endian"):
        read_ply(p)
    p.write_bytes(b"not a ply")
    with pytest.raises(InputError, match="not a PLY"):
        read_ply(p)
    p.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 1\nproperty float q\nend_header\n\0\0\0\0")
    with pytest.raises(InputError, match="no x y z"):
        read_ply(p)
    with pytest.raises(InputError, match="not found"):
        read_ply(tmp_path / "missing.ply")
    (tmp_path / "bad.las").write_bytes(b"LASF" + b"\0" * 50)
    with pytest.raises(InputError):
        read_las(tmp_path / "bad.las")
