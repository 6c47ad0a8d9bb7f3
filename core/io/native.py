"""The workspace's own block format: one JSON file holding a complete :class:`ImageBlock` in float64.

Python's JSON writer prints the shortest repr of every float, so a save/load round trip is exact. Rotations are
stored as OpenCV ``cam_from_world`` matrices, so no angle convention is involved.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import InputError
from ..model import CameraModel, GroundPoint, Image, ImageBlock, Pose, Rig, RigHead
from ..pipeline.atomic import write_json
from .validate import check_crs

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


def _numbers(values: Any, shape: tuple[int, ...], key: str, finite: bool = True) -> np.ndarray:
    """``values`` as a float64 array of ``shape``; InputError naming ``key`` otherwise (NaN and infinity only where
    ``finite`` is False)."""
    try:
        a = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("expected numbers", field=key) from None
    if a.shape != shape:
        raise InputError(f"expected shape {shape}, got {a.shape}", field=key)
    if finite and not np.all(np.isfinite(a)):
        raise InputError("contains NaN or infinity", field=key)
    return a


def _optional(d: dict, key: str, shape: tuple[int, ...]) -> np.ndarray | None:
    return None if d.get(key) is None else _numbers(d[key], shape, key)


def _count(d: dict, key: str) -> int:
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
        raise InputError(f"must be a positive integer, not {json.dumps(v)}", field=key)
    return v


def _text(d: dict, key: str, required: bool = True) -> str | None:
    v = d[key] if required else d.get(key)
    if v is None and not required:
        return None
    if not isinstance(v, str):
        raise InputError(f"must be a string, not {json.dumps(v)}", field=key)
    return v


def _read_pose(d: dict, key: str) -> Pose | None:
    """The pose under ``key``, a proper rotation, or None."""
    p = d.get(key)
    if p is None:
        return None
    if not isinstance(p, dict) or "R_cam_from_world" not in p or "C" not in p:
        raise InputError("expected an object with R_cam_from_world and C", field=key)
    r = _numbers(p["R_cam_from_world"], (3, 3), key + ".R_cam_from_world")
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-6 or np.linalg.det(r) < 0:
        raise InputError("not a proper rotation matrix", field=key + ".R_cam_from_world")
    return Pose(r, _numbers(p["C"], (3,), key + ".C"))


def _entries(d: dict, key: str, path: str, required: bool = True) -> list[dict]:
    """The objects listed under ``key`` (an empty list when an optional key is missing)."""
    if key not in d and not required:
        return []
    v = d.get(key)
    if not isinstance(v, list) or not all(isinstance(e, dict) for e in v):
        raise InputError("expected a list of objects" if key in d else "missing required key", path=path, field=key)
    return v


class _Entry:
    """Turns what goes wrong while one entry of a block file is read into an :class:`InputError` naming the file,
    the entry's line and the field (``cameras[cam1].fx``)."""

    def __init__(self, path: str, text: str | None, section: str, entry: dict, key: str) -> None:
        self.path, self.text, self.section, self.key, self.value = path, text, section, key, entry.get(key)
        self.where = f"{section}[{self.value}]"

    def __enter__(self) -> _Entry:
        return self

    def __exit__(self, kind: type | None, err: BaseException | None, tb: Any) -> bool:
        if err is None or not isinstance(err, (KeyError, InputError, TypeError, ValueError, AttributeError)):
            return False
        line = _line(self.text, self.section, self.key, self.value)  # only on error: a search through the text
        if isinstance(err, KeyError):
            raise InputError("missing required key", self.path, line, f"{self.where}.{err.args[0]}") from None
        if isinstance(err, InputError):
            raise InputError(err.reason, self.path, line, self.where + (f".{err.field}" if err.field else "")) from None
        raise InputError(str(err), self.path, line, self.where) from None


def _line(text: str | None, section: str, key: str, value: Any) -> int | None:
    """The 1-based line of ``"key": value`` after ``"section":`` in the file's ``text``, if found."""
    if text is None or value is None:
        return None
    start = text.find(json.dumps(section) + ":")
    at = text.find(f"{json.dumps(key)}: {json.dumps(value)}", max(start, 0))
    return None if at < 0 else text.count("\n", 0, at) + 1


def block_from_dict(d: dict[str, Any], path: str = "<dict>", text: str | None = None) -> ImageBlock:
    """Inverse of :func:`block_to_dict`; raises :class:`InputError` naming the entry (its line when the file's
    ``text`` is given) and the field on bad content."""
    if not isinstance(d, dict) or d.get("format") != "oblique_city.block":
        raise InputError("not an Oblique City block file", path=path, field="format")
    check_crs(d.get("crs"), path)  # a CRS pyproj knows; the block keeps the text as it was written
    if not isinstance(d.get("image_root"), (str, type(None))):
        raise InputError("must be a string or null", path=path, field="image_root")
    block = ImageBlock(crs=str(d["crs"]), image_root=d.get("image_root"))
    for c in _entries(d, "cameras", path):
        with _Entry(path, text, "cameras", c, "id"):
            vals = {k: float(_numbers(c[k], (), k)) for k in CAMERA_FIELDS[3:12] if k in c or k in CAMERA_FIELDS[3:7]}
            if min(vals["fx"], vals["fy"]) <= 0:
                raise InputError("focal lengths must be positive", field="fx" if vals["fx"] <= 0 else "fy")
            block.add_camera(CameraModel(id=_text(c, "id"), width=_count(c, "width"), height=_count(c, "height"),
                                         pixel_size_mm=None if c.get("pixel_size_mm") is None
                                         else float(_numbers(c["pixel_size_mm"], (), "pixel_size_mm")),
                                         name=_text(c, "name", False) or "", **vals))
    for r in _entries(d, "rigs", path, required=False):
        with _Entry(path, text, "rigs", r, "name"):
            block.rigs[_text(r, "name")] = Rig(r["name"], tuple(
                RigHead(_text(h, "name"), _text(h, "camera_id"),
                        _numbers(h["sensor_from_rig"], (3, 3), "sensor_from_rig"),
                        _numbers(h.get("lever_arm", [0.0] * 3), (3,), "lever_arm"))
                for h in _entries(r, "heads", path)))
    for i in _entries(d, "images", path):
        with _Entry(path, text, "images", i, "id"):
            block.add_image(Image(
                id=_text(i, "id"), camera_id=_text(i, "camera_id"), file=_text(i, "file", False),
                head=_text(i, "head", False), exposure=_text(i, "exposure", False),
                time=None if i.get("time") is None else float(_numbers(i["time"], (), "time")),
                pose_approx=_read_pose(i, "pose_approx"), pose_adjusted=_read_pose(i, "pose_adjusted"),
                sigma_position=_optional(i, "sigma_position", (3,)),
                sigma_attitude=_optional(i, "sigma_attitude", (3,))))
    for g in _entries(d, "ground_points", path, required=False):
        with _Entry(path, text, "ground_points", g, "name"):
            obs = g.get("observations", {})
            if not isinstance(obs, dict):
                raise InputError("must map image ids to pixels", field="observations")
            block.add_ground_point(GroundPoint(
                name=_text(g, "name"),
                xyz=None if g["xyz"] is None else _numbers(g["xyz"], (3,), "xyz", finite=False),
                sigma=_numbers(g["sigma"], (3,), "sigma", finite=False), kind=g["kind"],
                sigma_px=float(_numbers(g.get("sigma_px", 0.5), (), "sigma_px")),
                observations={k: _numbers(v, (2,), f"observations.{k}") for k, v in obs.items()}))
    return block


def write_block(block: ImageBlock, path: str | Path) -> None:
    """Save a block as JSON, atomically."""
    write_json(path, block_to_dict(block))


def read_block(path: str | Path) -> ImageBlock:
    """Load a block saved by :func:`write_block`."""
    path = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
        d = json.loads(text)
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except json.JSONDecodeError as e:
        raise InputError(f"invalid JSON: {e.msg}", path=path, line=e.lineno) from None
    except UnicodeDecodeError:
        raise InputError("not UTF-8 text", path=path) from None
    return block_from_dict(d, path, text)
