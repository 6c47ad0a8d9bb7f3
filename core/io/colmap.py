"""COLMAP sparse models (text or binary, read and written through pycolmap) as oriented image blocks.

* Pixels: COLMAP puts the origin at the outer corner of the top-left pixel (its centre is (0.5, 0.5)); the core
  at the pixel's centre. The reader subtracts 0.5 from the principal point, the writer adds it.
* Camera models mapped to the core's Brown model: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV and
  FULL_OPENCV when its rational terms k4 k5 k6 are zero. Any other model is refused with an error naming it.
  The writer uses PINHOLE without distortion, OPENCV without k3, FULL_OPENCV otherwise.
* Poses: COLMAP's ``cam_from_world`` uses OpenCV's camera axes, the same as the core.
* Georeference: a COLMAP model usually lives in an arbitrary frame. ``sim3=FILE`` gives the similarity
  ``X_world = scale * R @ X_colmap + t`` (COLMAP's ``model_aligner --transform_path`` output): either one line
  ``scale qw qx qy qz tx ty tz`` (COLMAP >= 3.9), a 3x4 or 4x4 matrix ``[scale R | t]`` (older COLMAP), or a JSON
  object ``{"scale": s, "rotation": [qw, qx, qy, qz] or 3x3, "translation": [tx, ty, tz]}``. The same can come
  from options ``sim3_scale``, ``sim3_rotation`` (quaternion w x y z) and ``sim3_translation``. The writer applies
  the inverse, so an exported model is in COLMAP's frame again. ``crs`` names the world CRS (required).
* Binary models are checked record by record before pycolmap reads them (:mod:`.colmap_binary`): a truncated or
  damaged file is refused naming it, where pycolmap could hang or read garbage.
* Image ids: the file name stem by default (``image_id=name`` keeps the whole relative name). 3D points are not
  imported (tie points come from the matching stage).
* Camera systems (COLMAP >= 3.12 ``rigs`` and ``frames``): the images of a frame of two or more images are one
  exposure (``frame<id>``), each with its camera's id as its head; a rig of two or more camera sensors whose
  mountings are known becomes a :class:`~..model.Rig` (``rig<id>``, the reference sensor first, lever arms scaled by
  the georeference; a rig with unknown mountings is estimated from the orientations, ``rig=auto``). The writer puts
  a block with one rig whose heads have cameras of their own, and whose every oriented image belongs to an
  exposure that follows the rig (:data:`RIG_TOLERANCE`), into one COLMAP rig with a frame per exposure; any other
  block gets a rig and a frame per camera and image, which carry every pose exactly (an adjusted block, whose
  heads the triangulation moved apart).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..geometry.rotations import orthonormalize, rotation_angle
from ..model import CameraModel, Image, ImageBlock, Pose, Rig, RigHead
from .colmap_binary import check_binary_model
from .common import finish_block
from .validate import check_crs, option_value, parse_bool, parse_float, reject_unknown

COLMAP_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
    "FULL_OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"),
}
"""COLMAP camera models the core can represent, with their parameter names."""

READER_OPTIONS: dict[str, str] = {
    "crs": "the world CRS (required)",
    "image_id": "stem (of the image name) or name",
    "sim3": "similarity file, world from model (model_aligner's output)",
    "sim3_scale": "its scale, without a file",
    "sim3_rotation": "its rotation, quaternion w x y z",
    "sim3_translation": "its translation",
}
"""The COLMAP reader's own options (see the module docstring)."""

RIG_TOLERANCE = (1e-6, 1e-9)
"""Metres and radians an image may be from where its exposure's rig puts it for the writer to give COLMAP the rig:
the poses read back are the block's within these (a block from the navigation data follows its rig to about 1e-9)."""


@dataclass(frozen=True)
class Similarity:
    """``X_world = scale * R @ X_model + t``."""

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, xyz: np.ndarray) -> np.ndarray:
        return self.scale * np.asarray(xyz) @ self.R.T + self.t

    def apply_pose(self, r_cam_from_model: np.ndarray, c_model: np.ndarray) -> Pose:
        """Pose in the world frame: rotation ``R_cam_from_model @ R^T``, centre transformed."""
        return Pose(r_cam_from_model @ self.R.T, self.apply(c_model[None])[0])

    def inverse(self) -> Similarity:
        return Similarity(1.0 / self.scale, self.R.T, -(self.R.T @ self.t) / self.scale)


def _quat_wxyz_to_matrix(q: np.ndarray, path: str | None, field: str) -> np.ndarray:
    q = np.asarray(q, dtype=np.float64)
    n = np.linalg.norm(q)
    if q.shape != (4,) or not np.isfinite(n) or abs(n - 1.0) > 1e-6:
        raise InputError(f"rotation quaternion must be 4 numbers of unit norm (w x y z), got {q.tolist()}",
                         path=path, field=field)
    w, x, y, z = q / n
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ])


def _rotation(value: Any, path: str | None, field: str) -> np.ndarray:
    a = np.asarray(value, dtype=np.float64)
    if a.shape == (3, 3):
        if np.abs(a @ a.T - np.eye(3)).max() > 1e-6 or np.linalg.det(a) < 0:
            raise InputError("rotation is not a rotation matrix", path=path, field=field)
        return orthonormalize(a)
    return _quat_wxyz_to_matrix(a, path, field)


def _from_matrix(m: np.ndarray, path: str) -> Similarity:
    sr = m[:3, :3]
    scale = float(np.cbrt(np.linalg.det(sr)))
    if not scale > 0:
        raise InputError("similarity matrix has no positive scale", path=path, field="sim3")
    return Similarity(scale, _rotation(sr / scale, path, "sim3"), m[:3, 3].copy())


def read_similarity(path: str | Path) -> Similarity:
    """Read a similarity file (see the module docstring for the three accepted layouts)."""
    p = Path(path)
    if not p.is_file():
        raise InputError("similarity file not found", path=p, field="sim3")
    text = p.read_text(encoding="utf-8-sig").strip()
    if text.startswith("{"):
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise InputError(f"invalid JSON: {e.msg}", path=p, line=e.lineno, field="sim3") from None
        try:
            return Similarity(float(d.get("scale", 1.0)), _rotation(d["rotation"], str(p), "rotation"),
                              np.asarray(d["translation"], dtype=np.float64).reshape(3))
        except KeyError as e:
            raise InputError("missing key", path=p, field=str(e.args[0])) from None
    values = []
    for i, line in enumerate(text.splitlines()):
        if line.strip().startswith("#"):
            continue
        values += [parse_float(v, p, i + 1, "sim3") for v in line.replace(",", " ").split()]
    a = np.array(values)
    if a.size == 8:
        return Similarity(float(a[0]), _quat_wxyz_to_matrix(a[1:5], str(p), "sim3"), a[5:8])
    if a.size in (12, 16):
        return _from_matrix(a.reshape(-1, 4), str(p))
    raise InputError(f"expected 8 numbers (scale qw qx qy qz tx ty tz) or a 3x4/4x4 matrix, got {a.size}",
                     path=p, field="sim3")


def _similarity_option(options: dict[str, Any], source: str) -> Similarity | None:
    path = options.pop("sim3", None)
    scale = options.pop("sim3_scale", None)
    rot = options.pop("sim3_rotation", None)
    trans = options.pop("sim3_translation", None)
    if path is not None:
        if scale is not None or rot is not None or trans is not None:
            raise InputError("give the georeference either as sim3=FILE or as sim3_scale/rotation/translation",
                             path=source, field="sim3")
        return read_similarity(str(path))
    if scale is None and rot is None and trans is None:
        return None
    r = np.eye(3) if rot is None else _rotation(option_value(rot), source, "sim3_rotation")
    t = np.zeros(3) if trans is None else np.asarray(option_value(trans), dtype=np.float64).reshape(3)
    s = 1.0 if scale is None else parse_float(scale, source, None, "sim3_scale")
    if s <= 0:
        raise InputError("sim3_scale must be positive", path=source, field="sim3_scale")
    return Similarity(s, r, t)


def _camera_from_colmap(cam, source: str) -> CameraModel:
    name = cam.model.name
    if name not in COLMAP_MODELS:
        raise InputError(f"COLMAP camera model {name} (camera {cam.camera_id}) cannot be represented by the "
                         f"Brown model; supported: {', '.join(COLMAP_MODELS)}", path=source, field="cameras")
    p = dict(zip(COLMAP_MODELS[name], np.asarray(cam.params, dtype=np.float64), strict=True))
    if any(p.get(k, 0.0) != 0.0 for k in ("k4", "k5", "k6")):
        raise InputError(f"FULL_OPENCV camera {cam.camera_id} has rational distortion k4..k6, which the Brown "
                         "model cannot represent", path=source, field="cameras")
    fx = p.get("fx", p.get("f"))
    fy = p.get("fy", p.get("f"))
    return CameraModel(id=str(cam.camera_id), width=int(cam.width), height=int(cam.height), fx=float(fx),
                       fy=float(fy), cx=float(p["cx"]) - 0.5, cy=float(p["cy"]) - 0.5,
                       **{k: float(p.get(k, 0.0)) for k in ("k1", "k2", "k3", "p1", "p2")})


def read_colmap(source: str, **options: Any) -> ImageBlock:
    """Read a COLMAP model folder (``cameras/images/points3D`` as ``.txt`` or ``.bin``)."""
    import pycolmap

    folder = Path(source)
    if not folder.is_dir():
        raise InputError("COLMAP model folder not found", path=source)
    if not any((folder / f"cameras.{ext}").is_file() for ext in ("txt", "bin")):
        raise InputError("no cameras.txt or cameras.bin in the folder", path=source, field="cameras")
    crs = check_crs(options.pop("crs", None), source, "crs")
    sim = _similarity_option(options, source)
    id_mode = str(options.pop("image_id", "stem")).lower()
    if id_mode not in ("stem", "name"):
        raise InputError(f"image_id must be stem or name, got '{id_mode}'", path=source, field="image_id")
    check_binary_model(folder)
    try:
        rec = pycolmap.Reconstruction(str(folder))
    except (RuntimeError, ValueError, IndexError, MemoryError) as e:
        raise InputError(f"COLMAP could not read the model: {str(e).splitlines()[-1][:200]}", path=source) from None
    block = ImageBlock(crs=crs, image_root=None)
    for cid in sorted(rec.cameras):
        block.add_camera(_camera_from_colmap(rec.cameras[cid], source))
    ids: dict[int, str] = {}
    for iid in sorted(rec.images):
        im = rec.images[iid]
        pose = None
        if im.has_pose:
            try:
                cfw = im.cam_from_world()
            except RuntimeError:  # a frame's pose through a rig sensor whose mounting the model lacks
                raise InputError(f"image {im.name}: no pose through its frame's rig (a sensor without its "
                                 "sensor_from_rig?)", path=source, field="rigs") from None
            r = np.asarray(cfw.rotation.matrix(), dtype=np.float64)
            c = -r.T @ np.asarray(cfw.translation, dtype=np.float64)
            pose = Pose(r, c) if sim is None else sim.apply_pose(r, c)
        image_id = im.name if id_mode == "name" else Path(im.name).stem
        if image_id in block.images:
            raise InputError(f"duplicate image id '{image_id}' (images {im.name}); try -o image_id=name",
                             path=source, field="images")
        block.add_image(Image(id=image_id, camera_id=str(im.camera_id), file=im.name, pose_approx=pose))
        ids[iid] = image_id
    if not block.images:
        raise InputError("the model has no images", path=source, field="images")
    _read_rigs(rec, ids, block, 1.0 if sim is None else sim.scale)
    return finish_block(block, source, options, "colmap")


def _read_rigs(rec, ids: dict[int, str], block: ImageBlock, scale: float) -> None:
    """The model's frames of two or more images as exposures, and the rigs they use as :class:`Rig` where every
    sensor is a camera with a known mounting (``ids``: COLMAP image id -> block image id; ``scale``: the
    georeference's, for the lever arms)."""
    import pycolmap

    frames: dict[int, list[str]] = {}
    for iid, image_id in ids.items():
        frames.setdefault(int(rec.images[iid].frame_id), []).append(image_id)
    rigs = set()
    for fid, members in frames.items():
        if len(members) > 1:
            for image_id in members:
                block.images[image_id].exposure = f"frame{fid}"
            rigs.add(int(rec.frames[fid].rig_id))
    camera = pycolmap.SensorType.CAMERA
    for rid in sorted(rigs):
        rig = rec.rigs[rid]
        ref, others = rig.ref_sensor_id, rig.non_ref_sensors
        if ref.type != camera or any(s.type != camera or t is None for s, t in others.items()):
            continue
        heads = [RigHead(str(ref.id), str(ref.id), np.eye(3))]
        for sensor, t in sorted(others.items(), key=lambda st: st[0].id):
            r = np.asarray(t.rotation.matrix(), np.float64)
            heads.append(RigHead(str(sensor.id), str(sensor.id), r, -scale * r.T @ np.asarray(t.translation)))
        block.rigs[f"rig{rid}"] = Rig(f"rig{rid}", tuple(heads))


def _rigid(r: np.ndarray, t: np.ndarray):
    """A ``pycolmap.Rigid3d`` ``x -> r x + t``."""
    import pycolmap

    return pycolmap.Rigid3d(np.hstack([r, np.reshape(t, (3, 1))]))


def _rig_frames(block: ImageBlock, images: list[Image], poses: dict[str, Pose], scale: float):
    """How COLMAP carries the block's camera system, or None where it cannot (see the module docstring): the rig's
    heads (reference first), each other head's ``sensor_from_rig`` ``(r, t)`` in the reference camera's frame (the
    COLMAP rig frame; lever arms times ``scale``, the model's units per metre), and per exposure its images (in the
    rig's head order) with the rig's ``rig_from_world`` ``r, t``, from ``poses`` (model frame)."""
    if len(block.rigs) != 1:
        return None
    (rig,) = block.rigs.values()
    heads = {h.name: h for h in rig.heads}
    if len({h.camera_id for h in rig.heads}) != len(rig.heads):
        return None
    ref = rig.heads[0]
    sensor_from_rig = {}
    for h in rig.heads:
        r, offset = h.relative_to(ref)
        sensor_from_rig[h.name] = (r, -r @ offset * scale)
    exposures: dict[str, list[Image]] = {}
    for img in images:
        h = heads.get(img.head) if img.exposure is not None else None
        if h is None or h.camera_id != img.camera_id:
            return None
        exposures.setdefault(img.exposure, []).append(img)
    order = list(heads)
    frames = []
    for members in exposures.values():
        members = sorted(members, key=lambda i: order.index(i.head))
        if len({i.head for i in members}) != len(members):
            return None
        r_h, t_h = sensor_from_rig[members[0].head]
        first = poses[members[0].id]
        r_rw, t_rw = r_h.T @ first.R, r_h.T @ (first.t - t_h)
        for img in members:
            r_h, t_h = sensor_from_rig[img.head]
            there = Pose.from_rt(r_h @ r_rw, r_h @ t_rw + t_h)
            pose = poses[img.id]
            if (np.linalg.norm(there.C - pose.C) / scale > RIG_TOLERANCE[0]
                    or rotation_angle(there.R, pose.R) > RIG_TOLERANCE[1]):
                return None
        frames.append((members, r_rw, t_rw))
    return rig.heads, sensor_from_rig, frames


def _camera_to_colmap(cam: CameraModel, camera_id: int):
    import pycolmap

    cx, cy = cam.cx + 0.5, cam.cy + 0.5
    if not cam.has_distortion:
        model, params = "PINHOLE", [cam.fx, cam.fy, cx, cy]
    elif cam.k3 == 0.0:
        model, params = "OPENCV", [cam.fx, cam.fy, cx, cy, cam.k1, cam.k2, cam.p1, cam.p2]
    else:
        model, params = "FULL_OPENCV", [cam.fx, cam.fy, cx, cy, cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, 0.0, 0.0,
                                        0.0]
    return pycolmap.Camera(model=model, width=cam.width, height=cam.height, params=params, camera_id=camera_id)


def write_colmap(block: ImageBlock, dest: str, binary: Any = False, sim3: str | None = None, **unknown: Any) -> None:
    """Write the oriented images of ``block`` as a COLMAP model folder (no 3D points).

    With ``sim3`` (a similarity file, world_from_model) the poses are written in the model frame. Images
    without orientation are left out (COLMAP images.txt always has a pose). Camera ids are 1..n in block order. A
    camera system goes in as a rig with a frame per exposure where COLMAP can carry it (see the module docstring).
    """
    import pycolmap

    reject_unknown(unknown, "colmap")

    inverse = None if sim3 is None else read_similarity(sim3).inverse()
    images = [img for img in block.images.values() if img.pose is not None]
    poses = {img.id: img.pose if inverse is None else inverse.apply_pose(img.pose.R, img.pose.C) for img in images}
    cam_ids = {cam.id: i for i, cam in enumerate(block.cameras.values(), start=1)}
    system = _rig_frames(block, images, poses, 1.0 if inverse is None else inverse.scale)
    rec = pycolmap.Reconstruction()
    rig_cams = set() if system is None else {h.camera_id for h in system[0]}
    for cam in block.cameras.values():
        add = rec.add_camera if cam.id in rig_cams else rec.add_camera_with_trivial_rig
        add(_camera_to_colmap(cam, cam_ids[cam.id]))
    image_ids = {img.id: n for n, img in enumerate(images, start=1)}
    if system is None:
        for img in images:
            pose = poses[img.id]
            rec.add_image_with_trivial_frame(pycolmap.Image(name=img.file or img.id, camera_id=cam_ids[img.camera_id],
                                                            image_id=image_ids[img.id]), _rigid(pose.R, pose.t))
    else:
        heads, sensor_from_rig, exposures = system
        sensor = {h.camera_id: pycolmap.sensor_t(type=pycolmap.SensorType.CAMERA, id=cam_ids[h.camera_id])
                  for h in heads}
        rig = pycolmap.Rig(rig_id=1)
        rig.add_ref_sensor(sensor[heads[0].camera_id])
        for h in heads[1:]:
            rig.add_sensor(sensor[h.camera_id], _rigid(*sensor_from_rig[h.name]))
        rec.add_rig(rig)
        for fid, (members, r, t) in enumerate(exposures, start=1):
            frame = pycolmap.Frame(frame_id=fid, rig_id=1, rig_from_world=_rigid(r, t))
            for img in members:
                frame.add_data_id(pycolmap.data_t(sensor[img.camera_id], image_ids[img.id]))
            rec.add_frame(frame)
            for img in members:
                im = pycolmap.Image(name=img.file or img.id, camera_id=cam_ids[img.camera_id],
                                    image_id=image_ids[img.id])
                im.frame_id = fid
                rec.add_image(im)
    out = Path(dest)
    out.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=".colmap.", dir=out))
    try:
        if parse_bool(binary, dest, None, "binary"):
            rec.write_binary(str(tmp))
        else:
            rec.write_text(str(tmp))
        for f in sorted(tmp.iterdir()):  # each file replaced atomically
            os.replace(f, out / f.name)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
