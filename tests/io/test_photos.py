"""Photographs deeper than 8 bits (12- and 14-bit values in 16-bit TIFF and PNG, four bands, float) read as the
8-bit image they hold, so that SIFT finds the same features; the significant bits a file declares (TIFF
MaxSampleValue, PNG sBIT) keep a dark image dark; unreadable files refused naming the file."""

from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np
import pytest

from oblique_city.core.errors import InputError
from oblique_city.core.io.photos import camera_bits, declared_bits, read_photo
from oblique_city.core.matching.features import sift_features
from oblique_city.core.model import CameraModel, Image, ImageBlock, Pose
from oblique_city.core.texture.sources import block_sources


def _scene(rng) -> np.ndarray:
    """An 8-bit BGR picture with structure at several scales (blurred noise, edges)."""
    img = np.zeros((300, 400, 3), np.float32)
    for sigma in (1.5, 4.0, 10.0):
        img += cv2.GaussianBlur(rng.normal(0, 60, (300, 400, 3)).astype(np.float32), (0, 0), sigma)
    img[100:180, 120:260] += 60
    return np.clip(img + 128, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("bits, ext", [(12, "tif"), (14, "tif"), (16, "tif"), (12, "png")])
def test_deep_photographs_read_as_the_8_bit_image_they_hold(tmp_path: Path, bits: int, ext: str):
    rng = np.random.default_rng(bits)
    bgr = _scene(rng)
    # the camera's values: the 8-bit picture on the sensor's full range, with noise in the bits below it
    scale = (2**bits - 1) / 255.0
    deep = np.clip(bgr * scale + rng.uniform(-0.4, 0.4, bgr.shape) * scale, 0, 2**bits - 1).astype(np.uint16)
    path = str(tmp_path / f"photo.{ext}")
    assert cv2.imwrite(path, deep)
    if bits == 12:
        assert cv2.imread(path, cv2.IMREAD_GRAYSCALE).max() <= 16  # OpenCV's own 8 bits: the top 8 of 16
    colour = read_photo(path, True)
    assert colour.dtype == np.uint8 and colour.shape == bgr.shape
    assert np.abs(colour.astype(int) - bgr).max() <= 1
    grey = read_photo(path, False)
    assert np.abs(grey.astype(int) - cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY)).max() <= 1
    uv, _ = sift_features(grey, 2000)
    uv8, _ = sift_features(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY), 2000)
    assert abs(len(uv) - len(uv8)) <= 0.05 * len(uv8) and len(uv8) > 100


def test_four_bands_and_float_photographs(tmp_path: Path):
    rng = np.random.default_rng(3)
    bgr = _scene(rng)
    nir = rng.integers(0, 4096, bgr.shape[:2]).astype(np.uint16)
    four = np.dstack([np.round(bgr * (4095 / 255.0)).astype(np.uint16), nir])  # B, G, R and near infrared
    assert cv2.imwrite(str(tmp_path / "rgbn.tif"), four)
    assert np.abs(read_photo(tmp_path / "rgbn.tif", True).astype(int) - bgr).max() <= 1
    import tifffile

    tifffile.imwrite(tmp_path / "float.tif", (bgr[:, :, ::-1] / 255.0).astype(np.float32), photometric="rgb")
    assert np.abs(read_photo(tmp_path / "float.tif", True).astype(int) - bgr).max() <= 1
    grey16 = np.round(cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY) * (4095 / 255.0)).astype(np.uint16)
    assert cv2.imwrite(str(tmp_path / "grey.tif"), grey16)
    assert read_photo(tmp_path / "grey.tif", True).shape == bgr.shape


def _with_sbit(png: bytes, bits: int, samples: int) -> bytes:
    """A PNG file's bytes with an sBIT chunk of ``bits`` per sample inserted after its header chunk."""
    import zlib

    data = bytes([bits] * samples)
    chunk = struct.pack(">I", len(data)) + b"sBIT" + data + struct.pack(">I", zlib.crc32(b"sBIT" + data))
    end = 8 + 8 + 13 + 4  # signature, IHDR length and type, its 13 bytes, its CRC
    return png[:end] + chunk + png[end:]


def test_a_dark_photograph_keeps_the_bits_its_file_declares(tmp_path: Path):
    """A dark 12-bit exposure (its brightest value 900, under 1024) is scaled by the 12 bits its file declares, as
    its neighbours are, not taken as a 10-bit one four times as bright; a file that declares nothing falls back on
    the smallest depth holding its maximum."""
    import tifffile

    rng = np.random.default_rng(5)
    grey = rng.integers(0, 901, (60, 80)).astype(np.uint16)
    grey[0, 0] = 900
    want = np.round(grey * (255.0 / 4095.0)).astype(int)
    tifffile.imwrite(tmp_path / "tagged.tif", grey, extratags=[(281, "H", 1, 4095, True)])
    assert declared_bits(str(tmp_path / "tagged.tif")) == 12
    assert np.abs(read_photo(tmp_path / "tagged.tif", False).astype(int) - want).max() <= 1
    ok, png = cv2.imencode(".png", grey)
    (tmp_path / "sbit.png").write_bytes(_with_sbit(png.tobytes(), 12, 1))
    assert declared_bits(str(tmp_path / "sbit.png")) == 12
    assert np.abs(read_photo(tmp_path / "sbit.png", False).astype(int) - want).max() <= 1
    colour = np.dstack([grey] * 3)
    ok, png = cv2.imencode(".png", colour)
    (tmp_path / "sbit3.png").write_bytes(_with_sbit(png.tobytes(), 12, 3))
    assert np.abs(read_photo(tmp_path / "sbit3.png", True).astype(int) - want[:, :, None]).max() <= 1
    # without a declaration: the 10 bits that hold 900
    assert cv2.imwrite(str(tmp_path / "plain.tif"), grey) and declared_bits(str(tmp_path / "plain.tif")) is None
    assert read_photo(tmp_path / "plain.tif", False).max() == 224


def test_a_dark_photograph_takes_the_depth_of_its_cameras_photographs(tmp_path: Path):
    """Files that declare nothing: the dark exposure of a 12-bit camera (brightest value 900) is read with the 12 bits
    the camera's other photographs need (as dark as they are), not as a 10-bit image four times as bright; an 8-bit
    camera beside it has no depth to give, and a photograph brighter than its camera's sample keeps its own."""
    rng = np.random.default_rng(6)
    block = ImageBlock(crs="EPSG:25832", image_root=str(tmp_path))
    for cam in ("deep", "plain"):
        block.add_camera(CameraModel(cam, 80, 60, 100.0, 100.0, 39.5, 29.5))
    for k in range(12):
        grey = rng.integers(0, 4001 if k != 5 else 901, (60, 80)).astype(np.uint16)
        grey[0, 0] = 4000 if k != 5 else 900
        assert cv2.imwrite(str(tmp_path / f"d{k}.tif"), grey)
        block.add_image(Image(f"d{k}", "deep", f"d{k}.tif", pose_adjusted=Pose(np.eye(3), (0.0, 0.0, 100.0))))
    cv2.imwrite(str(tmp_path / "p0.png"), np.full((60, 80), 100, np.uint8))
    block.add_image(Image("p0", "plain", "p0.png", pose_adjusted=Pose(np.eye(3), (0.0, 0.0, 100.0))))
    bits = camera_bits(block, sample=4)  # d0, d3, d7, d11: the dark d5 not among them
    assert bits == {"deep": 12, "plain": None}
    dark = tmp_path / "d5.tif"
    assert read_photo(dark, False).max() == 224  # alone: the 10 bits that hold 900
    assert read_photo(dark, False, "d5", bits["deep"]).max() == 56  # 900 * 255 / 4095
    assert read_photo(tmp_path / "d0.tif", False, "d0", 10).max() == 249  # brighter than the sample: its 12 bits
    # the stages' image sources carry the camera's depth
    by_id = {s.id: s for s in block_sources(block)}
    assert by_id["d5"].min_bits == 12 and by_id["p0"].min_bits is None


def test_unreadable_photograph_is_refused_naming_the_file(tmp_path: Path):
    bad = tmp_path / "broken.tif"
    bad.write_bytes(b"II*\x00" + b"\x00" * 20)
    with pytest.raises(InputError) as e:
        read_photo(bad, False, "S01_E001_nadir")
    assert "broken.tif" in str(e.value) and "S01_E001_nadir" in str(e.value)
