"""Options every block reader shares, applied once the reader has built its block in memory.

* ``gcps=FILE`` ground point list (:mod:`.gcp`), with ``gcp_columns``, ``gcp_delimiter``, ``gcp_crs`` (the
  points' CRS when it differs from the block's), ``gcp_sigma`` (metres, where the file has no sigma columns) and
  ``gcp_kind`` (default kind: control or check);
* ``measurements=FILE`` image measurements of ground points, with ``measurement_columns``,
  ``measurement_delimiter``, ``measurement_origin`` (``center`` or ``corner`` of the top-left pixel) and
  ``sigma_px``;
* ``image_root=DIR`` folder that relative image paths start from; ``check_images=true`` checks that every image
  file exists and has its camera's size (default: true when ``image_root`` is given);
* ``pose=approx`` (default: the imported orientation is a prior for aerial triangulation) or ``pose=adjusted``
  (it is final: stored as adjusted, and as approximate too).

Unknown options are an error, so a typo never passes silently.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import InputError
from ..model import ImageBlock
from .gcp import merge_ground_points, merge_measurements, read_ground_points, read_measurements
from .validate import check_block, check_image_files, parse_bool, parse_float, reject_unknown

COMMON_OPTIONS = ("gcps", "gcp_columns", "gcp_delimiter", "gcp_crs", "gcp_sigma", "gcp_kind", "measurements",
                  "measurement_columns", "measurement_delimiter", "measurement_origin", "sigma_px", "image_root",
                  "check_images", "pose")


def finish_block(block: ImageBlock, source: str | Path, options: dict[str, Any], fmt: str,
                 lines: dict[str, int] | None = None) -> ImageBlock:
    """Apply the shared options to a freshly read block, validate it, and return it.

    ``options`` are the reader's left-over options (consumed here; anything left is an error). ``lines`` maps
    image ids to the source line they came from, for error messages.
    """
    opts = dict(options)
    pose = str(opts.pop("pose", "approx")).lower()
    if pose not in ("approx", "adjusted"):
        raise InputError(f"pose must be approx or adjusted, got '{pose}'", path=source, field="pose")
    if pose == "adjusted":
        for img in block.images.values():
            img.pose_adjusted = img.pose_approx
    root = opts.pop("image_root", None)
    check = opts.pop("check_images", None)
    if root is not None:
        root_path = Path(str(root)).expanduser().resolve()
        if not root_path.is_dir():
            raise InputError(f"image folder not found: {root_path}", path=source, field="image_root")
        block.image_root = str(root_path)
    check_files = (root is not None) if check is None else parse_bool(check, source, None, "check_images")

    gcps = opts.pop("gcps", None)
    gcp_kw = {"columns": opts.pop("gcp_columns", None), "delimiter": opts.pop("gcp_delimiter", None),
              "kind": opts.pop("gcp_kind", "control")}
    gcp_sigma = opts.pop("gcp_sigma", None)
    if gcp_sigma is not None:
        gcp_kw["sigma"] = parse_float(gcp_sigma, source, None, "gcp_sigma")
    gcp_crs = opts.pop("gcp_crs", None)
    meas = opts.pop("measurements", None)
    meas_kw = {"columns": opts.pop("measurement_columns", None), "delimiter": opts.pop("measurement_delimiter", None),
               "origin": opts.pop("measurement_origin", "center")}
    sigma_px = opts.pop("sigma_px", None)
    reject_unknown(opts, fmt)

    if gcps is not None:
        merge_ground_points(block, read_ground_points(str(gcps), **gcp_kw), str(gcps), crs=gcp_crs)
    if meas is not None:
        merge_measurements(block, read_measurements(str(meas), **meas_kw), str(meas),
                           sigma_px=None if sigma_px is None else parse_float(sigma_px, meas, None, "sigma_px"))
    check_block(block, source)
    if check_files:
        check_image_files(block, source, lines)
    return block
