"""The sidebar tab "City" of the 3D viewport: the Block panel, the running job, and one panel per later stage.

Stage panels show each stage's status from ``state.json`` and Run buttons that call the generic
``city.run_stages`` operator, so they work for whichever stages are registered in ``core.pipeline.registry``; a
stage that is not registered yet is listed as such. The stages of ``addon.properties.STAGE_OPTION_GROUPS`` also show
their options, which read and write ``[stages.<stage>]`` of ``project.toml``. The Buildings panel lists the
buildings (:class:`CITY_UL_buildings`); making one active selects its object. The Ground Point Measurement panel
lists the ground points of the image the viewport looks through, to measure them by hand (:mod:`.overlay` draws them
over the image). Panels only read cached summaries (re-read when the files they come from change), never the
workspace on every redraw.
"""

from __future__ import annotations

import json
from pathlib import Path

import bpy

from ..addon import cameras, georef, jobs, layers_aerotri, layers_match, layers_windows
from ..addon.properties import option_fields
from ..core.aerotri.report import format_scale
from ..core.errors import CityError
from ..core.matching.manual import MANUAL_FILE, measurement_state, points_in_image
from ..core.model.exposures import MISSING_EXPOSURES
from ..core.pipeline.registry import get_stage, stage_names
from ..core.pipeline.workspace import ADJUSTED_BLOCK_FILE, BLOCK_FILE, STATE_FILE, Workspace

STAGE_PANELS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("Triangulation", ("match", "aerotri")),
    ("Dense & Surfaces", ("dense", "surface")),
    ("Buildings", ("buildings",)),
    ("Textures", ("texture",)),
    ("Windows", ("windows",)),
    ("Export", ("export",)),
)
"""Panel label -> the stages it shows, in pipeline order. Registered stages not named here go to "More Stages"."""

_cache: dict[tuple, object] = {}


def _mtime(path: Path) -> float | None:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return None


def _cached(key: tuple, compute):
    if key not in _cache:
        if len(_cache) > 64:
            _cache.clear()
        try:
            _cache[key] = compute()
        except (CityError, OSError, ValueError) as e:
            _cache[key] = {"error": str(e).splitlines()[0]}
    return _cache[key]


def _file_cached(path: Path, missing: dict, compute) -> dict:
    """``compute()`` of a file, re-run only when the file changed; ``missing`` while the file is not there."""
    key = (str(path), _mtime(path))
    if key[1] is None:
        return missing
    return _cached(key, compute)


def _figures_column(layout, context, summary):
    """The column of a panel's figures and the figures ``summary(root)``, or None when there is no workspace or the
    figures are an error (shown as one line)."""
    root = workspace_root(context)
    if root is None:
        return None
    s = summary(root)
    col = layout.column(align=True)
    if "error" in s:
        col.label(text=s["error"], icon="INFO")
        return None
    return col, s


def block_summary(root: Path) -> dict:
    """The block's summary (``ImageBlock.summary()``), re-read only when a block file changed."""
    key = ("block", str(root), _mtime(root / BLOCK_FILE), _mtime(root / ADJUSTED_BLOCK_FILE))
    if key[2] is None:
        return {"error": "no block imported yet"}
    return _cached(key, lambda: Workspace.open(root).load_block().summary())


def stage_state(root: Path) -> dict:
    """``state.json`` as a dict, re-read only when it changed."""
    path = root / STATE_FILE
    return _file_cached(path, {}, lambda: json.loads(path.read_text(encoding="utf-8")))


def workspace_root(context) -> Path | None:
    path = context.scene.oblique_city.workspace
    return Path(bpy.path.abspath(path)) if path else None


class CityPanel:
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "City"


class CITY_PT_block(CityPanel, bpy.types.Panel):
    bl_idname = "CITY_PT_block"
    bl_label = "Block"

    def draw(self, context):
        layout = self.layout
        scene = context.scene
        layout.prop(scene.oblique_city, "workspace")
        row = layout.row(align=True)
        row.operator("city.import_block", text="Import", icon="IMPORT")
        row.operator("city.open_workspace", text="Open", icon="FILE_FOLDER")
        row.operator("city.build_scene", text="Build", icon="FILE_REFRESH")
        root = workspace_root(context)
        if root is not None:
            s = block_summary(root)
            col = layout.column(align=True)
            if "error" in s:
                col.label(text=s["error"], icon="INFO")
            else:
                col.label(text=f"{s['images']} images, {s['cameras']} cameras, {s['adjusted']} adjusted")
                for view, n in s["views"].items():
                    col.label(text=f"    {view}: {n}")
                col.label(text=f"Ground points: {s['control_points']} control, {s['check_points']} check")
                if s["exposures"]:
                    col.label(text=f"Exposures: {s['exposures']}, rigs: {s['rigs']}")
                elif set(s["views"]) - {"nadir", "unoriented"}:
                    col.label(text=MISSING_EXPOSURES, icon="INFO")
                col.label(text=f"CRS: {s['crs'][:40]}")
        if georef.has_georef(scene):
            o = georef.get_origin(scene)
            layout.label(text=f"Origin: {o[0]:.3f}, {o[1]:.3f}, {o[2]:.3f}")
        row = layout.row(align=True)
        row.operator("city.view_image", icon="CAMERA_DATA")
        row.prop(scene.oblique_city, "undistort_backgrounds", text="", icon="IMAGE_BACKGROUND")
        row = layout.row()
        row.enabled = root is not None
        row.operator("city.open_project_report", icon="TEXT")


class CITY_PT_job(CityPanel, bpy.types.Panel):
    bl_idname = "CITY_PT_job"
    bl_label = "Job"

    def draw(self, context):
        layout = self.layout
        state = context.window_manager.oblique_city_job
        job = jobs.active_job()
        if job is not None and not job.finished:
            layout.progress(factor=state.fraction, text=state.message[:60] or state.stage)
            layout.operator("city.cancel_job", icon="CANCEL")
        elif state.status:
            layout.label(text=f"Last job: {state.status}", icon="CHECKMARK" if state.status == "done" else "ERROR")
            if state.message:
                layout.label(text=state.message[:80])
        row = layout.row(align=True)
        row.operator("city.run_stages", text="Run All Stages", icon="PLAY").stages = ""
        row.prop(context.scene.oblique_city, "force", text="", icon="FILE_REFRESH")


def draw_stages(layout, context, names: list[str]) -> None:
    """Status and a Run button for each stage; registered stages only get the button."""
    root = workspace_root(context)
    state = stage_state(root) if root is not None else {}
    registered = set(stage_names())
    running = jobs.active_job() is not None and not jobs.active_job().finished
    for name in names:
        box = layout.box()
        if name not in registered:
            box.label(text=f"{name}: not registered yet", icon="INFO")
            continue
        rec = state.get(name, {})
        status = rec.get("status", "pending")
        secs = f"  {rec['seconds']:.1f} s" if isinstance(rec.get("seconds"), (int, float)) else ""
        row = box.row()
        row.label(text=f"{name}: {status}{secs}", icon="CHECKMARK" if status == "done" else "DOT")
        sub = row.row()
        sub.enabled = root is not None and not running
        sub.operator("city.run_stages", text="Run", icon="PLAY").stages = name
        if rec.get("message"):
            box.label(text=str(rec["message"])[:80])
        try:
            description = get_stage(name).description
        except (CityError, ImportError) as e:  # a stage whose dependencies are missing still gets a panel line
            description = str(e).splitlines()[0]
        if description:
            box.label(text=description[:80])
        if option_fields(name):
            draw_stage_options(box, context, name, enabled=root is not None and not running)


def draw_stage_options(layout, context, name: str, enabled: bool = True) -> None:
    """The options of a stage of :data:`~addon.properties.STAGE_OPTION_GROUPS`: one field per option, stored in
    ``[stages.<name>]`` of ``project.toml`` (greyed out without a workspace or while a job runs)."""
    options = getattr(context.scene.oblique_city.stage_options, name)
    col = layout.column(align=True)
    col.use_property_split = True
    col.enabled = enabled
    col.label(text="Options (project.toml)", icon="PREFERENCES")
    for field in option_fields(name):
        col.prop(options, field)


def draw_export(layout, context) -> None:
    """The Export panel's buttons: the buildings to OBJ / CityGML / CityJSON, the oriented block to other
    software's formats."""
    col = layout.column()
    col.enabled = workspace_root(context) is not None
    col.operator("city.export_city_model", text="Export City Model", icon="EXPORT")
    col.operator("city.export_block", text="Export Oriented Block", icon="OUTLINER_OB_CAMERA")


def triangulation_summary(root: Path) -> dict:
    """The key figures of ``aerotri/report.json`` (:func:`addon.layers_aerotri.report_summary`), re-read only when
    the report changed."""
    path = root / layers_aerotri.REPORT_FILE
    return _file_cached(path, {"error": "no triangulation report yet"}, lambda: layers_aerotri.report_summary(path))


def _metres(v) -> str:
    return f"{v:.3f} m" if isinstance(v, (int, float)) and v == v else "-"


def graph_summary(root: Path) -> dict:
    """The connectivity graph's figures (:func:`addon.layers_match.graph_summary`), re-read only when it changed."""
    path = root / layers_match.GRAPH_FILE
    return _file_cached(path, {"error": "no connectivity graph yet"}, lambda: layers_match.graph_summary(path))


def targets_summary(root: Path) -> dict:
    """The target measurements' figures (:func:`addon.layers_match.targets_summary`), re-read only when they
    changed."""
    path = root / layers_match.TARGETS_FILE
    return _file_cached(path, {"error": "no target measurements yet"}, lambda: layers_match.targets_summary(path))


def draw_triangulation(layout, context) -> None:
    """The Triangulation panel's figures (the connectivity graph's pairs, the targets measured; mode, images, sigma0,
    check point RMS, the datum shift, blunders, the mounting calibration, the self-calibration, the camera with the
    largest systematic image residual, rejected control data and EO priors, the GNSS strip offsets, estimated or
    suspected, the weakest control point),
    the tie points' colourings and Open Report."""
    root = workspace_root(context)
    g = graph_summary(root) if root is not None else {"error": ""}
    if "error" not in g:
        median = f", median {g['median_matches']} matches" if g["median_matches"] is not None else ""
        layout.label(text=f"Connectivity graph: {g['pairs']} image pairs of {g['images']} images{median}")
    t = targets_summary(root) if root is not None else {"error": ""}
    if "error" not in t and t["mode"] != "none":
        versus = f", {t['imported_rms_px']:.2f} px RMS from imported" if t["imported_rms_px"] is not None else ""
        versus += f", {len(t['suspect'])} imported suspect" if t["suspect"] else ""
        layout.label(text=f"Targets measured: {t['measured']} ({t['missed']} not found{versus})")
    figures = _figures_column(layout, context, triangulation_summary)
    if figures is None:
        return
    col, s = figures
    mode = s["mode"] + (f" ({s['connection']})" if s["connection"] else "")
    col.label(text=f"Mode: {mode}, {s['images']} images")
    col.label(text=f"Sigma0: {s['sigma0']:.3f} ({s['sigma0_px']:.3f} px)")
    if s["tie_sigma"]:
        given, used = s["tie_sigma"]
        col.label(text=f"Tie sigma estimated: {used:.3f} px ({given:g} px given)")
    for part, f in s["prior_sigma"].items():
        col.label(text=f"{part} sigmas scaled by {format_scale(f)} (variance components)")
    if s["control_sigma"]:
        col.label(text=f"Control point measurement sigmas scaled by {s['control_sigma']:.2f} (variance component)")
    col.label(text=f"Check points ({s['check_n']}): RMS XY {_metres(s['check_rms_xy_m'])}, "
                   f"Z {_metres(s['check_rms_z_m'])}")
    if s["datum"]:
        shift, std = s["datum"]
        col.label(text="Datum shift: " + ", ".join(f"{v:.3f}" + (f" +- {d:.3f}" if std else "")
                                                  for v, d in zip(shift, std or shift)) + " m")
    col.label(text=f"Rejected observations: {s['blunder_percent']:.2f} %")
    if s["oblique_without_nadir"]:
        col.label(text=f"{s['oblique_without_nadir']} oblique images without a nadir image in their exposure: "
                       "import the exposures", icon="ERROR")
    if s["rig_fusion"]:
        n, deg, m = s["rig_fusion"]
        col.label(text=f"Heads of {n} exposures fused on the rig (moved {deg:.4f} deg, {m:.3f} m RMS)")
    if s["mounting"]:
        n, cam, angle = s["mounting"]
        col.label(text=f"Mounting calibrated for {n} cameras, largest boresight {angle:.4f} deg ({cam})")
    if s["self_calibration"]:
        n, cam, px, std, significant, tested = s["self_calibration"]
        sd = f" +- {std:.2f}" if std is not None else ""
        counted = f"; {significant} of {tested} corrections significant" if tested else ""
        col.label(text=f"Self-calibrated {n} cameras: a corner of {cam} moves {px:.2f}{sd} px{counted}")
    if s["systematic"]:
        cam, px = s["systematic"]
        col.label(text=f"Largest systematic image residual: {px:.3f} px ({cam})")
    if s["control_rejected"]:
        names, measurements = s["control_rejected"]
        col.label(text=f"Rejected control: {len(names)} points{' (' + ', '.join(names) + ')' if names else ''}, "
                       f"{measurements} measurements")
    if s["priors_rejected"]:
        positions, attitudes, images = s["priors_rejected"]
        shown = ", ".join(images[:PRIOR_IMAGES_SHOWN]) + (", ..." if len(images) > PRIOR_IMAGES_SHOWN else "")
        col.label(text=f"Rejected priors: {positions} GNSS positions, {attitudes} IMU attitudes ({shown})")
    if s["gnss_strips"]:
        n, strip, metres = s["gnss_strips"]
        col.label(text=f"GNSS offsets of {n} strips, largest {_metres(metres)} ({strip})")
    if s["strips_suspected"]:
        n, strip, metres = s["strips_suspected"]
        col.label(text=f"GNSS positions of {n} strips share an offset ({strip}: {_metres(metres)}): "
                       "try Shift per strip")
    if s["weakest_control"]:
        name, axis, metres = s["weakest_control"]
        col.label(text=f"Weakest control point: {name}, errors below {_metres(metres)} in {axis} pass its test")
    if s["prior_effect"]:
        metres, degrees = s["prior_effect"]
        parts = ([f"GNSS {_metres(metres)}"] if metres is not None else []) + (
            [f"IMU {degrees:.4f} deg"] if degrees is not None else [])
        col.label(text=f"Prior errors the tests miss move an image by at most: {', '.join(parts)}")
    row = layout.row(align=True)
    row.label(text="Colour tie points:")
    for value, label, _ in layers_aerotri.TIE_COLOURINGS:
        row.operator("city.colour_tie_points", text=label).colouring = value
    layout.operator("city.open_report", icon="URL")


PRIOR_IMAGES_SHOWN = 3
"""The Triangulation panel names at most this many images whose GNSS/IMU prior the adjustment rejected (all of
them are in the report)."""

BUILDING_LINES = 15
"""At most this many buildings that need attention (open solids, failures) are listed in the Buildings panel."""


def buildings_report(root: Path) -> dict:
    """``buildings/report.json`` as a dict, re-read only when it changed."""
    path = root / "buildings" / "report.json"
    return _file_cached(path, {"error": "no buildings report yet"},
                        lambda: json.loads(path.read_text(encoding="utf-8")))


class CITY_UL_buildings(bpy.types.UIList):
    """The Buildings panel's list: id, path, status (closed solid, open solid's problem, failure's reason),
    reconstruction seconds and surface count of each building."""

    bl_idname = "CITY_UL_buildings"

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index=0, flt_flag=0):
        symbol = "CANCEL" if item.failed else "CHECKMARK" if item.closed else "ERROR"
        if self.layout_type == "GRID":
            layout.label(text=item.name, icon=symbol)
            return
        row = layout.row(align=True)
        row.label(text=item.name, icon=symbol)
        row.label(text=item.path or "-")
        row.label(text=item.status)
        if not item.failed:
            row.label(text=f"{item.seconds:.1f} s, {item.surfaces} surf.")


BUILDING_LIST_ROWS = 6
"""Rows of the building list when it is not resized."""


def draw_buildings(layout, context) -> None:
    """The Buildings panel's per-building status: counts by path, closed solids, and the building list (every
    building with its status, failures with their reason; the active one is selected in the viewport). Before
    the list is filled (the layer is not built yet), the buildings that need attention are listed from the
    report instead."""
    root = workspace_root(context)
    if root is None:
        return
    rep = buildings_report(root)
    col = layout.column(align=True)
    if "error" in rep:
        col.label(text=rep["error"], icon="INFO")
        return
    done, failed = rep.get("buildings", []), rep.get("failures", [])
    paths = {p: sum(b.get("path") == p for b in done) for p in ("2d", "volumetric")}
    closed = sum(bool(b.get("closed")) for b in done)
    col.label(text=f"{len(done)} buildings (2D {paths['2d']}, volumetric {paths['volumetric']}), "
                   f"{closed} closed, {len(failed)} failed")
    settings = context.scene.oblique_city
    if len(settings.building_list):
        row = layout.row()
        row.template_list(CITY_UL_buildings.bl_idname, "", settings, "building_list", settings, "building_index",
                          rows=BUILDING_LIST_ROWS)
        row.operator("city.refresh_buildings", text="", icon="FILE_REFRESH")
        if 0 <= settings.building_index < len(settings.building_list):
            item = settings.building_list[settings.building_index]
            box = layout.box()
            box.label(text=f"{item.name}: {item.status}"[:80], icon="CANCEL" if item.failed else "OBJECT_DATA")
            if not item.failed:
                dormers = f", {item.dormers} dormers" if item.dormers else ""
                box.label(text=f"{item.path} path, {item.surfaces} surfaces{dormers}, {item.seconds:.1f} s")
                box.label(text=f"{item.roof_type} roof, {item.height_70p:.1f} m high (70 %), {item.volume:.0f} m3")
        return
    attention = [(b["id"], f"open solid: {b.get('solid_problem') or '?'}", "ERROR") for b in done
                 if not b.get("closed")] + [(f["id"], f"failed: {f.get('reason', '?')}", "CANCEL") for f in failed]
    for bid, text, icon in attention[:BUILDING_LINES]:
        col.label(text=f"{bid}  {text}"[:80], icon=icon)
    if len(attention) > BUILDING_LINES:
        col.label(text=f"... and {len(attention) - BUILDING_LINES} more (buildings/report.json)")
    layout.operator("city.refresh_buildings", text="List Buildings", icon="FILE_REFRESH")


WINDOW_LINES = 10
"""At most this many buildings (those with the most windows) are listed with their window count."""


def windows_summary(root: Path) -> dict:
    """The figures of ``windows/windows.json`` (:func:`addon.layers_windows.windows_summary`), re-read only when
    the file changed."""
    path = root / layers_windows.WINDOWS_FILE
    return _file_cached(path, {"error": "no windows yet"}, lambda: layers_windows.windows_summary(path))


def draw_windows(layout, context) -> None:
    """The Windows panel's figures: the window count, and the window count of the buildings with the most."""
    figures = _figures_column(layout, context, windows_summary)
    if figures is None:
        return
    col, s = figures
    col.label(text=f"{s['windows']} windows on {s['walls']} walls of {len(s['buildings'])} buildings "
                   f"({s['grid']} from the facade grid)")
    for bid, n in list(s["buildings"].items())[:WINDOW_LINES]:
        col.label(text=f"    {bid}: {n}"[:80])
    if len(s["buildings"]) > WINDOW_LINES:
        col.label(text=f"... and {len(s['buildings']) - WINDOW_LINES} more buildings")


PANEL_EXTRAS = {"Triangulation": draw_triangulation, "Buildings": draw_buildings, "Windows": draw_windows,
                "Export": draw_export}
"""Panel label -> a function ``(layout, context)`` drawing that panel's own content under its stages."""


def _stage_panel(label: str, names: tuple[str, ...]) -> type:
    ident = "CITY_PT_" + "".join(c if c.isalnum() else "_" for c in label.lower())

    def draw(self, context):
        draw_stages(self.layout, context, list(names))
        if label in PANEL_EXTRAS:
            PANEL_EXTRAS[label](self.layout, context)

    return type(ident, (CityPanel, bpy.types.Panel),
                {"bl_idname": ident, "bl_label": label, "bl_options": {"DEFAULT_CLOSED"}, "draw": draw})


MEASURE_LINES = 20
"""The Ground Point Measurement panel lists at most this many points of the image looked through."""


def ground_point_rows(root: Path, image_id: str) -> dict:
    """``{"rows": [...]}``: :func:`core.matching.manual.points_in_image` of ``image_id``, from the workspace's
    measurement state re-read only when the block, the target measurements or the manual measurements changed (a
    block of thousands of images is not read again for every image looked through)."""
    files = (BLOCK_FILE, ADJUSTED_BLOCK_FILE, layers_match.TARGETS_FILE, MANUAL_FILE)
    key = ("ground points", str(root), *(_mtime(root / f) for f in files))
    if key[2] is None:
        return {"error": "no block imported yet"}
    state = _cached(key, lambda: {"state": measurement_state(Workspace.open(root))})
    if "error" in state:
        return state
    return _cached((*key, image_id), lambda: {"rows": points_in_image(state["state"], image_id)})


class CITY_PT_ground_points(CityPanel, bpy.types.Panel):
    """The ground points of the image the viewport looks through: where each is measured and from what (imported,
    targets, manual, removed), with buttons to measure one by clicking its target, remove or reset a measurement."""

    bl_idname = "CITY_PT_ground_points"
    bl_label = "Ground Point Measurement"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        layout = self.layout
        root = workspace_root(context)
        viewed = cameras.viewed_image(context.scene)
        if root is None or viewed is None:
            layout.label(text="Look through an image (View Through Image) to measure its ground points", icon="INFO")
            return
        layout.label(text=f"Image {viewed[1]}")
        row = layout.row()
        row.prop(context.scene.oblique_city, "measure_refine")
        row.prop(context.scene.oblique_city, "show_ground_points")
        found = ground_point_rows(root, viewed[1])
        if "error" in found:
            layout.label(text=found["error"], icon="INFO")
            return
        rows = found["rows"]
        if not rows:
            layout.label(text="No ground point in this image")
        for r in rows[:MEASURE_LINES]:
            row = layout.row(align=True)
            where = "not measured" if r.uv is None else f"({r.uv[0]:.1f}, {r.uv[1]:.1f})"
            row.label(text=f"{r.name} ({r.kind}): {where}, {r.source}")
            row.operator("city.measure_ground_point", text="", icon="RESTRICT_SELECT_OFF").point = r.name
            if r.uv is not None:
                op = row.operator("city.edit_ground_measurement", text="", icon="X")
                op.point, op.action = r.name, "remove"
            if r.source in ("manual", "removed"):
                op = row.operator("city.edit_ground_measurement", text="", icon="LOOP_BACK")
                op.point, op.action = r.name, "reset"
        if len(rows) > MEASURE_LINES:
            layout.label(text=f"... and {len(rows) - MEASURE_LINES} more (oblique-city measure lists them all)")


class CITY_PT_more_stages(CityPanel, bpy.types.Panel):
    bl_idname = "CITY_PT_more_stages"
    bl_label = "More Stages"
    bl_options = {"DEFAULT_CLOSED"}

    @staticmethod
    def extra_stages() -> list[str]:
        named = {n for _, names in STAGE_PANELS for n in names}
        return [n for n in stage_names() if n not in named]

    @classmethod
    def poll(cls, context):
        return bool(cls.extra_stages())

    def draw(self, context):
        draw_stages(self.layout, context, self.extra_stages())


STAGE_PANEL_CLASSES = tuple(_stage_panel(label, names) for label, names in STAGE_PANELS)
CLASSES = (CITY_UL_buildings, CITY_PT_block, CITY_PT_job, *STAGE_PANEL_CLASSES, CITY_PT_ground_points,
           CITY_PT_more_stages)
