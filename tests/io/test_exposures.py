"""Exposures and the camera system of a block imported from a plain OPK list: found by time or by name, the rig
estimated from the approximate orientations against the simulator's nominal rig."""

from __future__ import annotations

import numpy as np
import pytest

from oblique_city.core.errors import InputError
from oblique_city.core.geometry.rotations import rotation_angle, rotvec_to_matrix
from oblique_city.core.io.formats import read_block, write_block
from oblique_city.core.model import Image, ImageBlock, Pose
from oblique_city.core.model.exposures import describe_system, estimate_rig, rig_fit

NAME_PATTERN = r"(?P<exposure>S\d+_E\d+)_(?P<head>[a-z]+)"


def _partition(block: ImageBlock) -> set[frozenset[str]]:
    groups: dict[str, set[str]] = {}
    for img in block.images.values():
        groups.setdefault(img.exposure, set()).add(img.id)
    return {frozenset(g) for g in groups.values()}


def _relative(rig, head: str) -> tuple[np.ndarray, np.ndarray]:
    """A head's mounting relative to the rig's first head: rotation and offset in that head's frame."""
    ref, h = rig.heads[0], rig.head(head)
    return h.sensor_from_rig @ ref.sensor_from_rig.T, ref.sensor_from_rig @ (h.lever_arm - ref.lever_arm)


def test_opk_carries_exposures_heads_and_times(tmp_path, penta_block):
    write_block("opk", penta_block, tmp_path / "b.txt")
    back = read_block("opk", str(tmp_path / "b.txt"))
    for img in penta_block.images.values():
        got = back.images[img.id]
        assert (got.exposure, got.head, got.time) == (img.exposure, img.head, img.time)
    # the list has no rig: one is estimated, with the nadir head (it looks down) as its reference
    assert list(back.rigs) == ["system"] and back.rigs["system"].heads[0].name == "nadir"
    assert describe_system(back).startswith(f"{len(_partition(penta_block))} exposures of 5 heads; rig 'system'")


@pytest.mark.parametrize("by", ["time", "name"])
def test_exposures_found_by_time_or_name_and_the_rig_estimated(tmp_path, penta_block, plain_opk, by):
    plain_opk(penta_block, tmp_path / "c.txt", jitter_s=0.002)
    plain = read_block("opk", str(tmp_path / "c.txt"))
    assert all(img.exposure is None for img in plain.images.values()) and not plain.rigs
    opts = {"exposures": "time", "exposure_tolerance": 0.005} if by == "time" else \
        {"exposures": "name", "exposure_pattern": NAME_PATTERN}
    back = read_block("opk", str(tmp_path / "c.txt"), **opts)
    assert _partition(back) == _partition(penta_block)
    if by == "name":
        assert all(back.images[i].head == img.head for i, img in penta_block.images.items())
    # the navigation orientations go through the nominal rig, so the estimate is that rig (to the OPK text's digits)
    est = back.rigs["system"]
    nominal = penta_block.rigs["penta"]
    heads = {back.images[i].head: img.head for i, img in penta_block.images.items()}  # camera id -> head
    assert heads[est.heads[0].name] == nominal.heads[0].name == "nadir"
    for h in est.heads[1:]:
        r_est, t_est = _relative(est, h.name)
        r_nom, t_nom = _relative(nominal, heads[h.name])
        assert np.degrees(rotation_angle(r_est, r_nom)) < 1e-9 and np.linalg.norm(t_est - t_nom) < 1e-9
    assert all(f.rotation_rms_deg < 1e-9 and f.offset_rms_m < 1e-9 for f in rig_fit(back, est))


def test_rig_estimate_leaves_out_wrong_exposures_and_reports_the_spread(penta_block):
    """Orientations from an earlier adjustment scatter about the rig (0.003 degrees and 0.02 m per axis per image
    here), and three exposures carry a 1-degree error in one head: the estimate leaves those out, lands within its
    standard error of the nominal rig, and its fit reports the scatter."""
    block = ImageBlock(crs=penta_block.crs, cameras=penta_block.cameras)
    rng = np.random.default_rng(4)
    sig_r, sig_c = np.radians(0.003), 0.02
    wrong = {f"S01_E00{k}_left" for k in (2, 3, 4)}
    for img in penta_block.images.values():
        p = img.pose_approx
        rot = rotvec_to_matrix(rng.normal(0, sig_r, 3) + (np.radians([1.0, 0, 0]) if img.id in wrong else 0.0))
        block.add_image(Image(id=img.id, camera_id=img.camera_id, head=img.head, exposure=img.exposure,
                                  pose_approx=Pose(rot @ p.R, p.C + rng.normal(0, sig_c, 3))))
    est, fits = estimate_rig(block)
    nominal = penta_block.rigs["penta"]
    n = len(_partition(block))
    by_head = {f.head: f for f in fits}
    assert by_head["left"].left_out == 3 and all(f.left_out == 0 for f in fits if f.head != "left")
    for f in fits:
        # the relative rotation scatters by sqrt(2) sigma per axis: an angle of sqrt(6) sigma RMS; the offset by
        # sqrt(2) sigma per axis: sqrt(6) sigma RMS in 3-D
        assert f.rotation_rms_deg == pytest.approx(np.degrees(sig_r) * np.sqrt(6), rel=0.15)
        assert f.offset_rms_m == pytest.approx(sig_c * np.sqrt(6), rel=0.15)
        r_est, t_est = _relative(est, f.head)
        r_nom, t_nom = _relative(nominal, f.head)
        m = f.exposures
        assert rotation_angle(r_est, r_nom) < 4 * sig_r * np.sqrt(2) * np.sqrt(3) / np.sqrt(m)
        assert np.linalg.norm(t_est - t_nom) < 4 * sig_c * np.sqrt(2) * np.sqrt(3) / np.sqrt(m)
        assert m == n - (3 if f.head == "left" else 0)


def test_bad_exposure_options_name_the_file_line_and_field(tmp_path, penta_block, plain_opk):
    plain_opk(penta_block, tmp_path / "c.txt")
    src = str(tmp_path / "c.txt")
    first_row = 1 + next(k for k, t in enumerate((tmp_path / "c.txt").read_text().splitlines())
                         if t.startswith("S01_E001_nadir"))
    with pytest.raises(InputError) as e:  # a tolerance longer than the time between exposures merges them
        read_block("opk", src, exposures="time", exposure_tolerance=10.0)
    assert e.value.field == "time" and e.value.path == src and "same head" in str(e.value)
    with pytest.raises(InputError) as e:
        read_block("opk", src, exposures="name", exposure_pattern=r"(S\d+)_E\d+_[a-z]+x")
    assert (e.value.field, e.value.line, e.value.path) == ("name", first_row, src)
    with pytest.raises(InputError) as e:
        read_block("opk", src, exposures="name", exposure_pattern=r"S\d+_E\d+_[a-z]+")
    assert e.value.field == "exposure_pattern" and "group" in str(e.value)
    with pytest.raises(InputError) as e:
        read_block("opk", src, exposures="by_magic")
    assert e.value.field == "exposures"
    # a list without times cannot give exposures by time
    lines = (tmp_path / "c.txt").read_text().splitlines()
    cols = lines[first_row - 2].split()
    k = cols.index("time")
    (tmp_path / "d.txt").write_text("\n".join(lines[:first_row - 2] + [" ".join(c for j, c in enumerate(t.split())
                                                                                if j != k)
                                                                       for t in lines[first_row - 2:]]) + "\n")
    with pytest.raises(InputError) as e:
        read_block("opk", str(tmp_path / "d.txt"), exposures="time")
    assert (e.value.field, e.value.line) == ("time", first_row)
