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
  (it is final: stored as adjusted, and as approximate too);
* ``exposures=given`` (default: as the format gives them), ``time`` (images whose times follow each other within
  ``exposure_tolerance`` seconds, default 0.01) or ``name`` (``exposure_pattern``, a regular expression over the
  whole image id whose group ``exposure``, else its first, names the exposure and whose group ``head`` names the
  head), see :mod:`..model.exposures`;
* ``rig=auto`` (default: a block with exposures of two or more heads and no rig gets one estimated from its
  approximate orientations, :func:`..model.exposures.estimate_rig`) or ``rig=none``.

An option that serves another (``exposure_pattern`` with ``exposures=name``, the ``gcp_*`` options with ``gcps``,
...: :data:`NEEDS`) is refused without it.

Unknown options are an error, so a typo never passes silently.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ..errors import InputError
from ..model import ImageBlock
from ..model.exposures import assign_exposures, estimate_rig, image_head
from .gcp import merge_ground_points, merge_measurements, read_ground_points, read_measurements
from .validate import check_block, check_image_files, parse_bool, parse_float, reject_unknown

COMMON_OPTIONS: dict[str, str] = {
    "gcps": "ground point list (CSV or text)",
    "gcp_columns": "its columns, e.g. name,x,y,z,sx,sy,sz,kind",
    "gcp_delimiter": "its delimiter (comma, semicolon, tab, whitespace)",
    "gcp_crs": "its CRS when it differs from the block's",
    "gcp_sigma": "metres, where it has no sigma columns",
    "gcp_kind": "control or check, where it has no kind column",
    "measurements": "image measurements of the ground points",
    "measurement_columns": "their columns, e.g. name,image,u,v",
    "measurement_delimiter": "their delimiter",
    "measurement_origin": "center or corner of the top-left pixel",
    "sigma_px": "their standard deviation, pixels",
    "image_root": "folder relative image paths start from",
    "check_images": "true: every image file exists and has its camera's size",
    "pose": "approx (a prior for aerial triangulation) or adjusted (final)",
    "exposures": "given, time or name: which images one trigger of a multi-head camera took",
    "exposure_tolerance": "seconds between the images of one exposure (exposures=time)",
    "exposure_pattern": "regular expression over the image id, groups exposure and head (exposures=name)",
    "rig": "auto (estimate the camera system's rig from the orientations) or none",
}
"""The options every reader but the native one takes (see the module docstring), with a line of help each."""

NEEDS: dict[str, tuple[str, str | None]] = {
    **{k: ("gcps", None) for k in ("gcp_columns", "gcp_delimiter", "gcp_kind", "gcp_sigma", "gcp_crs")},
    **{k: ("measurements", None) for k in ("measurement_columns", "measurement_delimiter", "measurement_origin",
                                           "sigma_px")},
    "exposure_tolerance": ("exposures", "time"), "exposure_pattern": ("exposures", "name")}
"""Shared options that do something only with another one (option -> that option and the value it needs, None for
any): given without it they are refused, so that a forgotten ``-o exposures=name`` does not pass unnoticed."""


def finish_block(block: ImageBlock, source: str | Path, options: dict[str, Any], fmt: str,
                 lines: dict[str, int] | None = None) -> ImageBlock:
    """Apply the shared options to a freshly read block, validate it, and return it.

    ``options`` are the reader's left-over options (consumed here; anything left is an error). ``lines`` maps
    image ids to the source line they came from, for error messages.
    """
    opts = dict(options)
    for key, (needed, value) in NEEDS.items():
        given = opts.get(needed)
        if key in opts and (given is None or (value is not None and str(given).lower() != value)):
            raise InputError(f"{key} is used only with -o {needed}={value or '...'}", path=source, field=key)
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
    exposures = str(opts.pop("exposures", "given")).lower()
    pattern = opts.pop("exposure_pattern", None)
    tolerance = parse_float(opts.pop("exposure_tolerance", 0.01), source, None, "exposure_tolerance")
    rig = str(opts.pop("rig", "auto")).lower()
    if rig not in ("auto", "none"):
        raise InputError(f"rig must be auto or none, got '{rig}'", path=source, field="rig")
    reject_unknown(opts, fmt)

    if exposures != "given":
        assign_exposures(block, exposures, None if pattern is None else str(pattern), tolerance, source, lines)
    for img in block.images.values():
        if img.exposure is not None:
            img.head = image_head(img)
    if rig == "auto" and not block.rigs and len({img.head for img in block.images.values()
                                                 if img.exposure is not None}) >= 2:
        try:
            est, _ = estimate_rig(block)
        except InputError as e:
            raise InputError(f"{e.reason} (rig=none imports the block without a rig)", path=source,
                             field=e.field) from None
        block.rigs[est.name] = est

    if gcps is not None:
        merge_ground_points(block, read_ground_points(str(gcps), **gcp_kw), str(gcps), crs=gcp_crs)
    if meas is not None:
        merge_measurements(block, read_measurements(str(meas), **meas_kw), str(meas),
                           sigma_px=None if sigma_px is None else parse_float(sigma_px, meas, None, "sigma_px"))
    check_block(block, source)
    if check_files:
        check_image_files(block, source, lines)
    return block
