"""BlocksExchange rotation conventions: every CameraOrientation, matrix and omega/phi/kappa, against an
independent construction (axes from the orientation's name, angles through scipy)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oblique_city.core.geometry.projection import project
from oblique_city.core.geometry.rotations import opk_to_cam_from_world
from oblique_city.core.io.blocksexchange import CAMERA_ORIENTATIONS
from oblique_city.core.io.formats import read_block

AXIS = {"Right": [1.0, 0.0, 0.0], "Left": [-1.0, 0.0, 0.0], "Down": [0.0, 1.0, 0.0], "Up": [0.0, -1.0, 0.0]}


def bex_axes(name: str) -> np.ndarray:
    """Rows: the BlocksExchange camera axes in OpenCV camera coordinates, read from the orientation's name."""
    x_dir, y_dir = name[1:].split("Y")
    x, y = np.array(AXIS[x_dir]), np.array(AXIS[y_dir])
    return np.array([x, y, np.cross(x, y)])


XML = """<?xml version="1.0"?>
<BlocksExchange version="3.2">
  <SpatialReferenceSystems><SRS><Id>0</Id><Definition>EPSG:25832</Definition></SRS></SpatialReferenceSystems>
  <Block><SRSId>0</SRSId><Photogroups><Photogroup><Name>g</Name>
    <ImageDimensions><Width>3000</Width><Height>2000</Height></ImageDimensions>
    <FocalLengthPixels>4000</FocalLengthPixels><CameraOrientation>{orient}</CameraOrientation>
    <PrincipalPoint><x>1510.25</x><y>990.75</y></PrincipalPoint>
    <Photo><Id>1</Id><ImagePath>m.jpg</ImagePath><Pose><Rotation>{matrix}</Rotation>
      <Center><x>512000</x><y>5404000</y><z>900</z></Center></Pose></Photo>
    <Photo><Id>2</Id><ImagePath>a.jpg</ImagePath><Pose><Rotation>{angles}</Rotation>
      <Center><x>512000</x><y>5404000</y><z>900</z></Center></Pose></Photo>
  </Photogroup></Photogroups></Block>
</BlocksExchange>
"""


@pytest.mark.parametrize("orient", sorted(CAMERA_ORIENTATIONS))
def test_camera_orientation_matrix_and_angles(tmp_path, orient):
    r_opencv = opk_to_cam_from_world(np.radians(44.0), np.radians(-3.0), np.radians(121.0))  # an oblique view
    m = bex_axes(orient) @ r_opencv  # world -> BlocksExchange camera axes
    matrix = "".join(f"<M_{i}{j}>{m[i, j]!r}</M_{i}{j}>" for i in range(3) for j in range(3))
    omega, phi, kappa = Rotation.from_matrix(m.T).as_euler("XYZ", degrees=True)  # M^T = Rx Ry Rz (intrinsic)
    angles = f"<Omega>{omega!r}</Omega><Phi>{phi!r}</Phi><Kappa>{kappa!r}</Kappa>"
    (tmp_path / "b.xml").write_text(XML.format(orient=orient, matrix=matrix, angles=angles))
    b = read_block("bex", tmp_path / "b.xml")
    assert np.abs(b.images["m"].pose.R - r_opencv).max() < 1e-14
    assert np.abs(b.images["a"].pose.R - r_opencv).max() < 1e-12
    # principal point in pixels is independent of the orientation (image axes, centre-of-pixel origin)
    assert (b.cameras["g"].cx, b.cameras["g"].cy) == (1510.25, 990.75)


def test_spec_example_nadir_angles():
    """The specification's example: M close to diag(-1, 1, -1) with Omega 179.65, Phi 0.05, Kappa 179.91."""
    m = np.array([[-0.9999982912233401, -0.001636319085375301, -0.0008602425863163225],
                  [-0.001631068695467463, 0.9999802528616577, -0.00606906089589293],
                  [0.0008701565192966738, -0.006067647409696231, -0.9999812130648239]])
    omega, phi, kappa = Rotation.from_matrix(m.T).as_euler("XYZ", degrees=True)
    assert (omega, phi, kappa) == pytest.approx((179.6523471469934, 0.04985630236313049, 179.9065465708369),
                                                abs=1e-9)


def test_written_block_projects_like_the_core(tmp_path, oblique_block):
    """A ground point projects to the same pixel from the written XML's own numbers (matrix, centre, K)."""
    from lxml import etree

    from oblique_city.core.io.formats import write_block

    write_block("bex", oblique_block, tmp_path / "b.xml")
    root = etree.parse(str(tmp_path / "b.xml")).getroot()
    photo = root.find(".//Photo")
    rot = photo.find("Pose/Rotation")
    m = np.array([[float(rot.findtext(f"M_{i}{j}")) for j in range(3)] for i in range(3)])
    c = np.array([float(photo.findtext(f"Pose/Center/{t}")) for t in "xyz"])
    pg = photo.getparent()
    f = float(pg.findtext("FocalLengthPixels"))
    cx, cy = float(pg.findtext("PrincipalPoint/x")), float(pg.findtext("PrincipalPoint/y"))
    fy = f * float(pg.findtext("AspectRatio"))
    img = oblique_block.images[photo.findtext("ImagePath").split(".")[0]]
    cam = oblique_block.camera_of(img)
    xyz = img.pose.C + 300.0 * img.pose.R[2] + [5.0, -7.0, 0.0]
    xc = m @ (xyz - c)
    uv_ref = np.array([f * xc[0] / xc[2] + cx, fy * xc[1] / xc[2] + cy])
    uv, _ = project(cam.with_distortion(), img.pose, xyz[None])
    assert np.abs(uv[0] - uv_ref).max() < 1e-9
