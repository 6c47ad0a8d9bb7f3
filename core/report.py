"""The project report: one self-contained HTML page on a workspace, like the processing reports of photogrammetry
software (``oblique-city report WS``, Blender "Project Report").

It gathers what the stages left in the workspace: the block (images per view, cameras, ground points), every stage's
status, time, summary and metrics from ``state.json`` (stages not run are listed as such), the aerial
triangulation's quality layers (``aerotri/layers/*.png``) with a link to its own report, a table of the buildings
(path, closed solid, roof type, heights, footprint, volume, windows) and pictures of the surface: the true
orthophoto with the building outlines of ``buildings/buildings.json`` drawn over it, the DSM as a coloured hillshade
and the forward intersection error map. Pictures are downscaled to at most ``max_side`` pixels and embedded as PNG,
so the page can be mailed on its own.
"""

from __future__ import annotations

import argparse
import datetime
import html
from pathlib import Path
from typing import Any

import numpy as np

from .aerotri.report import colourise, format_value, png_base64
from .errors import WorkspaceError
from .pipeline import Workspace
from .pipeline.atomic import write_text
from .pipeline.registry import get_stage, stage_names

REPORT_FILE = "report.html"
AEROTRI_LAYERS = ("cba_rays", "intersection_error_before", "intersection_error_after")


def hillshade(dsm: np.ndarray, cell: float, azimuth_deg: float = 315.0, altitude_deg: float = 45.0) -> np.ndarray:
    """Shaded relief ``(rows, cols)`` in 0..1 of a height grid ``dsm (rows, cols)`` (NaN cells: 0), lit from
    ``azimuth_deg`` (clockwise from north) at ``altitude_deg``."""
    z = np.where(np.isfinite(dsm), dsm, np.nanmin(dsm) if np.isfinite(dsm).any() else 0.0)
    gy, gx = np.gradient(z, cell)  # rows run south: gy is -dz/dnorth
    slope = np.arctan(np.hypot(gx, gy))
    aspect = np.arctan2(-gy, -gx)  # direction of steepest descent, counter-clockwise from east
    az = np.radians(90.0 - azimuth_deg)
    alt = np.radians(altitude_deg)
    shade = np.sin(alt) * np.cos(slope) + np.cos(alt) * np.sin(slope) * np.cos(az - aspect)
    return np.where(np.isfinite(dsm), np.clip(shade, 0.0, 1.0), 0.0)


def _downscale(rgb: np.ndarray, max_side: int) -> np.ndarray:
    import cv2

    scale = max_side / max(rgb.shape[:2])
    if scale >= 1.0:
        return rgb
    size = (max(1, round(rgb.shape[1] * scale)), max(1, round(rgb.shape[0] * scale)))
    return cv2.resize(rgb, size, interpolation=cv2.INTER_AREA)


def _figure(rgb: np.ndarray, caption: str, max_side: int) -> str:
    img = _downscale(np.ascontiguousarray(rgb[..., :3]), max_side)
    return (f"<figure><img alt='{html.escape(caption)}' src='data:image/png;base64,{png_base64(img)}' "
            f"width='{img.shape[1]}' height='{img.shape[0]}'><figcaption>{html.escape(caption)}</figcaption>"
            "</figure>")


def _metric_rows(metrics: dict[str, Any], prefix: str = "") -> list[tuple[str, str]]:
    """Flattened ``(name, value)`` rows of a stage's metrics (nested dicts joined with '.', long lists cut)."""
    rows = []
    for k, v in metrics.items():
        name = f"{prefix}{k}"
        if isinstance(v, dict):
            rows += _metric_rows(v, name + ".")
        elif isinstance(v, list) and len(v) > 8:
            rows.append((name, f"{len(v)} values: {format_value(v[:4])}, ..."))
        else:
            rows.append((name, format_value(v)))
    return rows


def _surface_figures(ws: Workspace, max_side: int) -> list[str]:
    import cv2

    from .buildings.model import load_buildings
    from .io.geotiff import read_geotiff

    out = []
    ortho_path = ws.path("surface", "ortho.tif")
    if ortho_path.exists():
        ortho = read_geotiff(ortho_path)
        rgb = np.ascontiguousarray(ortho.data[..., :3]).copy()
        n = 0
        if ws.path("buildings", "buildings.json").exists():
            buildings, _ = load_buildings(ws.path("buildings", "buildings.json"))
            width = max(1, round(max(rgb.shape[:2]) / max_side))
            for b in buildings:
                fp = np.asarray(b.footprint, dtype=np.float64)
                px = np.column_stack([(fp[:, 0] - ortho.x0) / ortho.cell, (ortho.y0 - fp[:, 1]) / ortho.cell])
                cv2.polylines(rgb, [np.round(px).astype(np.int32)], True, (255, 40, 40), width, cv2.LINE_AA)
                n += 1
        out.append(_figure(rgb, f"true orthophoto, {ortho.cell:.3f} m cells" +
                           (f", {n} building outlines" if n else ""), max_side))
    dsm_path = ws.path("surface", "dsm.tif")
    if dsm_path.exists():
        dsm = read_geotiff(dsm_path)
        d = dsm.data.astype(np.float64)
        shade = hillshade(d, dsm.cell)
        colour = colourise(d).astype(np.float64) / 255.0
        rgb = np.round(255 * colour * (0.35 + 0.65 * shade[..., None])).astype(np.uint8)
        fin = d[np.isfinite(d)]
        span = f"{fin.min():.1f} to {fin.max():.1f} m" if len(fin) else "empty"
        out.append(_figure(rgb, f"DSM, {span}, {np.isfinite(d).mean():.1%} of the cells measured", max_side))
    q_path = ws.path("surface", "quality_adjusted.png")
    if q_path.exists():
        q = cv2.imread(str(q_path), cv2.IMREAD_COLOR)[:, :, ::-1]
        out.append(_figure(q, "forward intersection error of the dense points (adjusted orientation)", max_side))
    return out


def _building_table(ws: Workspace) -> str:
    """One row per building: reconstruction path, closed solid, roof type, heights, areas, volume, windows."""
    from .buildings.attributes import building_attributes
    from .buildings.model import load_buildings

    buildings, _ = load_buildings(ws.path("buildings", "buildings.json"))
    windows: dict[str, int] = {}
    if ws.path("windows", "windows.json").exists():
        from .windows.store import load_windows

        for w in load_windows(ws.path("windows", "windows.json")):
            windows[w.building_id] = windows.get(w.building_id, 0) + 1
    head = ("building", "path", "closed", "roof type", "ground [m]", "height 70 % [m]", "max height [m]",
            "footprint [m2]", "volume [m3]", "surfaces", "windows")
    rows = []
    for b in buildings:
        a = building_attributes(b)
        cells = (b.id, b.path, "yes" if b.info.get("closed") else "no", a["roof_type"], a["ground_height"],
                 a["roof_height_70p"] - a["ground_height"], a["measured_height"], a["footprint_area"], a["volume"],
                 len(b.surfaces), windows.get(b.id, 0))
        rows.append("<tr>" + "".join(f"<td>{format_value(c)}</td>" for c in cells) + "</tr>")
    return ("<table><tr>" + "".join(f"<th>{h}</th>" for h in head) + "</tr>" + "".join(rows) + "</table>")


def project_report(ws: Workspace, max_side: int = 900) -> str:
    """The report page of workspace ``ws`` (see the module docstring)."""
    import cv2

    from .geometry.crs import parse_crs

    state = ws.read_state()
    parts = [f"<h1>Oblique City project report: {html.escape(ws.root.name)}</h1>",
             f"<p>{html.escape(str(ws.root.resolve()))}; CRS {html.escape(parse_crs(ws.crs).name)}; written "
             f"{datetime.datetime.now().astimezone().isoformat(timespec='seconds')}</p>"]
    if ws.has_block():
        s = ws.load_block().summary()
        views = ", ".join(f"{v} {n}" for v, n in s["views"].items())
        parts.append(f"<h2>Block</h2><p>{s['images']} images ({views}), {s['cameras']} cameras, "
                     f"{s['control_points']} control and {s['check_points']} check points, "
                     f"{s['adjusted']} adjusted orientations.</p>")
    else:
        parts.append("<h2>Block</h2><p>no block imported yet.</p>")
    rows = []
    stages = [get_stage(n) for n in stage_names()]
    for stage in stages:
        st = state.get(stage.name, {})
        secs = st.get("seconds")
        rows.append(f"<tr><td>{stage.name}</td><td>{html.escape(st.get('status', 'not run'))}</td>"
                    f"<td>{'-' if secs is None else f'{secs:.1f}'}</td>"
                    f"<td style='text-align:left'>{html.escape(st.get('message', '') or stage.description)}</td></tr>")
    total = sum(st.get("seconds") or 0.0 for st in state.values())
    parts.append("<h2>Processing</h2><table><tr><th>stage</th><th>status</th><th>seconds</th><th>summary</th></tr>"
                 + "".join(rows) + f"</table><p>total {total:.0f} s</p>")
    for stage in stages:
        metrics = state.get(stage.name, {}).get("metrics")
        section = []
        if metrics:
            body = "".join(f"<tr><td style='text-align:left'>{html.escape(k)}</td><td>{v}</td></tr>"
                           for k, v in _metric_rows(metrics))
            section.append(f"<table>{body}</table>")
        if stage.name == "aerotri":
            if ws.path("aerotri", "report.html").exists():
                uri = ws.path("aerotri", "report.html").resolve().as_uri()
                section.append(f"<p><a href='{uri}'>the aerial triangulation's own report</a></p>")
            for name in AEROTRI_LAYERS:
                p = ws.path("aerotri", "layers", f"{name}.png")
                if p.exists():
                    section.append(_figure(cv2.imread(str(p), cv2.IMREAD_COLOR)[:, :, ::-1],
                                           name.replace("_", " "), max_side // 2))
        if stage.name == "surface":
            section += _surface_figures(ws, max_side)
        if stage.name == "buildings" and ws.path("buildings", "buildings.json").exists():
            section.append(_building_table(ws))
        if section:
            parts.append(f"<h2>{html.escape(stage.name)}</h2>" + "".join(section))
    style = ("body{font-family:sans-serif;margin:2em;max-width:1100px}table{border-collapse:collapse;margin:4px 0}"
             "td,th{border:1px solid #ccc;padding:3px 8px;text-align:right}figure{display:inline-block;margin:8px}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{html.escape(ws.root.name)}</title>"
            f"<style>{style}</style></head><body>" + "".join(parts) + "</body></html>")


def write_project_report(workspace: str | Path, out: str | Path | None = None, max_side: int = 900) -> Path:
    """Write the project report of ``workspace`` (atomically) to ``out`` (default ``WS/report.html``)."""
    ws = Workspace.open(workspace)
    path = Path(out) if out is not None else ws.root / REPORT_FILE
    if path.is_dir():
        raise WorkspaceError(f"{path} is a folder: give the report's file name")
    write_text(path, project_report(ws, max_side))
    return path


def cmd_report(args: argparse.Namespace) -> int:
    print(f"project report written to {write_project_report(args.workspace, args.out)}")
    return 0


def add_commands(sub) -> None:
    s = sub.add_parser("report", help="write the project report (HTML: block, stages, metrics, pictures)")
    s.add_argument("workspace")
    s.add_argument("--out", help=f"output file (default WS/{REPORT_FILE})")
    s.set_defaults(func=cmd_report)
