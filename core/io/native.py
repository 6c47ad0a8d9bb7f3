"""The workspace's own block format: one JSON file holding a complete :class:`ImageBlock` in float64.

Python's JSON writer prints the shortest repr of every float, so a save/load round trip is exact. Rotations are
stored as OpenCV ``cam_from_world`` matrices, so no angle convention is involved.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..model import CameraModel, GroundPoint, Image, ImageBlock, Pose, Rig, RigHead
from ..pipeline.atomic import write_json

FORMAT_VERSION = 1
CAMERA_FIELDS = ("id", "width", "height", "fx", "fy", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "pixel_size_mm",
                 "name")


def _arr(a: np.ndarray | None) -> list | None:
    return None if a is None else np.asarray(a, dtype=np.float64).tolist()


def _pose(p: Pose | None) -> dict | None:
    return None if p is None else {"R_cam_from_world": p.R.tolist(), "C": p.C.tolist()}


def block_to_dict(block: ImageBlock) -> dict[str, Any]:
    """Plain JSON-ready dict of a block."""
    return {
        "format": "oblique_city.block", "version": FORMAT_VERSION, "crs": block.crs,
        "image_root": block.image_root,
        "cameras": [{k: getattr(c, k) for k in CAMERA_FIELDS} for c in block.cameras.values()],
        "rigs": [{"name": r.name, "heads": [{"name": h.name, "camera_id": h.camera_id,
                                              "sensor_from_rig": h.sensor_from_rig.tolist(),
                                              "lever_arm": h.lever_arm.tolist()} for h in r.heads]}
                 for r in block.rigs.values()],
        "images": [{"id": i.id, "camera_id": i.camera_id, "file": i.file, "head": i.head, "exposure": i.exposure,
                    "time": i.time, "pose_approx": _pose(i.pose_approx), "pose_adjusted": _pose(i.pose_adjusted),
                    "sigma_position": _arr(i.sigma_position), "sigma_attitude": _arr(i.sigma_attitude)}
                   for i in block.images.values()],
        "ground_points": [{"name": g.name, "xyz": _arr(g.xyz), "sigma": _arr(g.sigma), "kind": g.kind,
                           "sigma_px": g.sigma_px,
                           "observations": {k: _arr(v) for k, v in g.observations.items()}}
                          for g in block.ground_points.values()],
    }


def _finite(values: list, where: str, path: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("expected numbers", path=path, field=where) from None
    if a.shape != shape:
        raise InputError(f"expected shape {shape}, got {a.shape}", path=path, field=where)
    if not np.all(np.isfinite(a)):
        raise InputError("contains NaN or infinity", path=path, field=where)
    return a


def _read_pose(d: dict | None, where: str, path: str) -> Pose | None:
    if d is None:
        return None
    return Pose(_finite(d["R_cam_from_world"], where + ".R_cam_from_world", path, (3, 3)),
                _finite(d["C"], where + ".C", path, (3,)))


def block_from_dict(d: dict[str, Any], path: str = "<dict>") -> ImageBlock:
    """Inverse of :func:`block_to_dict`; raises :class:`InputError` naming the field on bad content."""
    if d.get("format") != "oblique_city.block":
        raise InputError("not an Oblique City block file", path=path, field="format")
    try:
        block = ImageBlock(crs=d["crs"], image_root=d.get("image_root"))
        for c in d["cameras"]:
            vals = {k: c[k] for k in CAMERA_FIELDS if k in c}
            for k in ("fx", "fy", "cx", "cy"):
                if not math.isfinite(float(vals[k])):
                    raise InputError("not a finite number", path=path, field=f"cameras[{c['id']}].{k}")
            block.add_camera(CameraModel(**vals))
        for r in d.get("rigs", []):
            block.rigs[r["name"]] = Rig(r["name"], tuple(RigHead(**h) for h in r["heads"]))
        for i in d["images"]:
            where = f"images[{i['id']}]"
            block.add_image(Image(
                id=i["id"], camera_id=i["camera_id"], file=i.get("file"), head=i.get("head"),
                exposure=i.get("exposure"),
                time=None if i.get("time") is None else float(_finite(i["time"], where + ".time", path, ())),
                pose_approx=_read_pose(i.get("pose_approx"), where + ".pose_approx", path),
                pose_adjusted=_read_pose(i.get("pose_adjusted"), where + ".pose_adjusted", path),
                sigma_position=None if i.get("sigma_position") is None else np.asarray(i["sigma_position"]),
                sigma_attitude=None if i.get("sigma_attitude") is None else np.asarray(i["sigma_attitude"]),
            ))
        for g in d.get("ground_points", []):
            block.add_ground_point(GroundPoint(
                name=g["name"], xyz=None if g["xyz"] is None else np.asarray(g["xyz"]),
                sigma=np.asarray(g["sigma"]), kind=g["kind"], sigma_px=float(g.get("sigma_px", 0.5)),
                observations={k: np.asarray(v, dtype=np.float64) for k, v in g["observations"].items()},
            ))
    except KeyError as e:
        raise InputError("missing required key", path=path, field=str(e.args[0])) from None
    except InputError as e:
        if e.path is None:
            raise InputError(e.reason, path=path, field=e.field) from None
        raise
    return block


def write_block(block: ImageBlock, path: str | Path) -> None:
    """Save a block as JSON, atomically."""
    write_json(path, block_to_dict(block))


def read_block(path: str | Path) -> ImageBlock:
    """Load a block saved by :func:`write_block`."""
    path = str(path)
    try:
        with open(path, encoding="utf-8") as f:
            d = json.load(f)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except json.JSONDecodeError as e:
        raise InputError(f"invalid JSON: {e.msg}", path=path, line=e.lineno) from None
    return block_from_dict(d, path)
