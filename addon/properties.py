"""Add-on preferences, persistent scene settings and transient job state.

* :class:`CityPreferences` (``bl_idname`` = the extension's root package, which is ``bl_ext.<repo>.oblique_city``
  inside Blender and ``oblique_city`` outside): how jobs run (child process or thread) and where a stage's
  independent units go (in-process, local processes, a Dask scheduler).
* :class:`CitySceneSettings` on ``Scene.oblique_city``, saved in the .blend: the workspace folder, display
  options and the per-building list of the Buildings panel (:class:`CityBuildingItem`, filled by
  :func:`.layers_buildings.fill_building_list`; making an item active selects that building's object). The
  georeference (CRS, float64 origin) is not here: see :mod:`.georef`.
* ``Scene.oblique_city.stage_options.<stage>``: the options of the stages in :data:`OPTION_STAGES` (those whose
  module imports), one property per field of the stage's config dataclass. They store nothing in the .blend:
  reading one reads ``[stages.<stage>]`` of the workspace's ``project.toml`` (cached until the file changes; a
  missing key is the config's default), setting one writes that key there, as ``oblique_city run --set
  stage.key=value`` does, so the panel, the CLI and the runner share one set of options.
* :class:`CityJobState` on ``WindowManager.oblique_city_job``, never saved: the running job's progress.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import bpy
from bpy.props import (
    BoolProperty,
    CollectionProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from ..core.errors import CityError
from ..core.pipeline import Workspace
from ..core.pipeline.registry import get_stage
from ..core.pipeline.stage import Range
from ..core.pipeline.workspace import PROJECT_FILE
from .jobs import ExecutorSettings
from .layers_buildings import select_building

ROOT_PACKAGE = __package__.rpartition(".")[0]
"""The extension's package name, as Blender knows it."""


class CityPreferences(bpy.types.AddonPreferences):
    bl_idname = ROOT_PACKAGE

    job_mode: EnumProperty(
        name="Run Jobs In",
        items=[("subprocess", "Child Process", "Run stages in a separate Python process (a crash in a stage cannot "
                "take Blender down)"),
               ("thread", "Background Thread", "Run stages in a thread of Blender's own process")],
        default="subprocess",
    )
    executor: EnumProperty(
        name="Executor",
        items=[("inline", "In Process", "Independent units one after the other"),
               ("processes", "Local Processes", "A pool of local worker processes"),
               ("dask", "Dask", "A Dask cluster: the scheduler below, or a local cluster when empty")],
        default="inline",
    )
    workers: IntProperty(name="Workers", default=2, min=1, max=256)
    scheduler: StringProperty(name="Dask Scheduler", description="e.g. tcp://10.0.0.5:8786", default="")

    def draw(self, context):
        layout = self.layout
        layout.prop(self, "job_mode")
        layout.prop(self, "executor")
        row = layout.row()
        row.prop(self, "workers")
        row.prop(self, "scheduler")


OPTION_STAGES = ("match", "aerotri", "dense", "surface", "buildings", "windows")
"""The stages whose options their panel edits (``Scene.oblique_city.stage_options.<stage>``)."""

OPTION_HINTS: dict[str, dict[str, dict[str, Any]]] = {
    "match": {
        "targets": {"items": (("none", "None", "The ground points' image measurements as imported"),
                              ("missing", "Missing", "Measure the signalised targets where the import has no "
                                                     "measurement"),
                              ("all", "All", "Measure every signalised target in every image, in place of the "
                                             "imported measurements"))},
        "target_disc_radius_m": {"description": "Radius of the targets' bright disc (m; 0: a bright "
                                                             "square alone)"},
        "target_square_half_m": {"description": "Half side of the targets' dark square (m; 0: a disc "
                                                             "alone)"},
        "target_pattern": {"items": (("disc", "Disc", "A bright disc on a dark square, a disc or a bright square "
                                                      "alone"),
                                     ("checker", "Checkerboard", "A square in two by two fields, opposite ones "
                                                                 "alike"),
                                     ("cross", "Cross", "Two bright bars crossing at the centre, reaching the "
                                                        "square's half side from it"))},
        "target_bar_half_m": {"description": "Half width of a cross's bars (m)"},
        "target_square_azimuth": {"description": "Direction of the squares' sides, degrees counterclockwise from the "
                                                 "grid's x axis, or 'estimate' (found in each image)"},
        "target_search_px": {"description": "Search radius around the predicted position (px)"},
        "target_min_score": {"description": "Correlation a target measurement needs"},
    },
    "aerotri": {
        "mode": {"items": (("integrated", "Integrated (IAT)", "All images in one adjustment"),
                           ("hierarchical", "Hierarchical (HAT)", "Nadir block first, then each oblique view tied "
                                                                  "to it by connection points"))},
        "connection": {"items": (("cba", "CBA", "Per grid cell the tie point with most rays"),
                                 ("2", ">= 2 rays", "Every tie point with at least 2 nadir rays"),
                                 ("3", ">= 3 rays", "Every tie point with at least 3 nadir rays"),
                                 ("5", ">= 5 rays", "Every tie point with at least 5 nadir rays"),
                                 ("10", ">= 10 rays", "Every tie point with at least 10 nadir rays"))},
        "cell_size": {"description": "CBA grid cell (m)"},
        "self_calibration": {"items": (("focal", "Focal", "Focal length"),
                                       ("principal_point", "Principal point", "Principal point"),
                                       ("radial", "Radial", "Radial distortion k1 k2 k3"),
                                       ("tangential", "Tangential", "Tangential distortion p1 p2"))},
        "sigma_px": {"description": "A priori sigma of the tie measurements (px)"},
        "tie_sigma_estimate": {"description": "Estimate the tie measurements' sigma from their residuals and adjust "
                                              "again with it when it differs from the given one"},
        "tie_sigma_tolerance": {"description": "Relative difference between the estimated and the given tie sigma "
                                               "that makes the adjustment run again"},
        "prior_sigma_estimate": {"description": "Scale the GNSS and IMU sigmas up by their variance components and "
                                                "adjust again when the errors exceed them"},
        "control_sigma_estimate": {"description": "Scale the control points' image measurement sigmas by their "
                                                  "variance component and adjust again when their residuals differ "
                                                  "from them"},
        "prior_sigma_tolerance": {"description": "Share by which a GNSS or IMU variance factor must exceed 1 to make "
                                                 "the adjustment run again"},
        "calibration_images": {"description": "HAT with self-calibration: images nearest the block's centre (all "
                                              "views) that calibrate the cameras before the runs (0: each run)"},
        "calibration_std_max_images": {"description": "With self- or mounting calibration, runs of up to this many "
                                                      "images get the calibration's standard deviations and "
                                                      "correlations"},
        "rig": {"description": "Tie the heads of each exposure to the block's rig: they share their exposure's "
                               "one GNSS/IMU measurement (IAT: rig constraints; HAT: the heads fused after the runs)"},
        "rig_sigma_deg": {"description": "Rig constraints' boresight sigma (degrees about each camera axis)"},
        "rig_sigma_m": {"description": "Rig constraints' lever-arm sigma (m along each camera axis)"},
        "mounting": {"description": "Calibrate each camera's boresight and lever arm against the GNSS/IMU priors"},
        "control_tests": {"description": "Test the control points' measurements and coordinates for blunders"},
        "prior_tests": {"description": "Test each image's GNSS position and IMU attitude prior for blunders"},
        "gnss_strips": {"items": (("off", "Off", "The GNSS positions carry noise only (a PPK trajectory)"),
                                  ("shift", "Shift per strip", "Estimate a GNSS offset per flight strip"),
                                  ("drift", "Shift and drift", "Estimate a GNSS offset and a drift along each "
                                                               "flight strip"))},
        "gnss_shift_sigma": {"description": "A priori sigma of a strip's GNSS offset (m)"},
        "gnss_drift_sigma": {"description": "A priori sigma of a strip's GNSS drift (m per km)"},
        "blunder_threshold": {"description": "Normalised residual above which an observation is "
                                                         "rejected"},
        "linear_solver": {"items": (("auto", "Automatic", "Chosen from the block's size and structure"),
                                    ("sparse_schur", "Sparse Schur", "Sparse factorisation of the camera system"),
                                    ("explicit_schur", "Explicit Schur", "Conjugate gradients on the explicit "
                                                                         "camera system"),
                                    ("iterative_schur", "Iterative Schur", "Conjugate gradients, implicit"))},
        "layer_views": {"items": (("all", "All", "CBA layers from all views"),
                                  ("nadir", "Nadir", "CBA layers from the nadir views"),
                                  ("oblique", "Oblique", "CBA layers from the oblique views"))},
    },
    "buildings": {
        "min_height": {"description": "Lowest building above the terrain (nDSM, m)"},
        "min_area": {"description": "Smallest building footprint (m^2)"},
        "use_masks": {"description": "Use the surface stage's building and vegetation masks (else roughness "
                                     "rejects vegetation)"},
        "footprints": {"description": "GeoJSON file of user footprints, workspace-relative or absolute "
                                      "(empty: detect the buildings)"},
        "voxel": {"description": "Noise filter cube (m, 0 = guessed)"},
        "force_path": {"items": (("", "Automatic", "Each building takes the path its shape calls for"),
                                 ("2d", "2D", "Footprint and roof planes for every building"),
                                 ("volumetric", "Volumetric", "Volumetric reconstruction for every building"))},
        "max_overhang": {"description": "Widest roof overhang searched (m)"},
        "overhang_thickness": {"description": "Thickness of the overhang slab (m)"},
        "dormers": {"description": "Model dormers on the sloped roofs (blocks of points above their slope)"},
        "dormer_min_rise": {"description": "Height above its slope that marks a dormer (m)"},
        "max_roof_fit": {"description": "Models that miss their roof points by more than this on "
                                                    "average are refused as no building (m, 0 = keep all)"},
    },
    "windows": {
        "polarity": {"items": (("auto", "Automatic", "Per facade, the cue that finds clearly more window area"),
                               ("dark", "Darker", "Windows darker than the wall"),
                               ("bright", "Lighter", "Windows lighter than the wall"),
                               ("colour", "Colour", "Windows of another colour than the wall (glass on brick)"))},
        "min_score": {"description": "Least score of a written window"},
        "k_sigma": {"description": "Threshold in robust standard deviations of the wall's contrast"},
        "min_contrast": {"description": "Least relative contrast of a window texel"},
        "bar_m": {"description": "Glazing bars up to this width are bridged: one window, not two "
                                             "panes (m, 0 = off)"},
    },
    "dense": {
        "sgm_mode": {"items": (("sgbm_3way", "SGBM 3-way", "OpenCV's fast 3-way SGBM"),
                               ("sgbm", "SGBM 5 paths", "OpenCV's single-pass SGBM"),
                               ("hh", "Full SGM (8 paths)", "Full SGM, slower and more memory"),
                               ("hh4", "HH4", "OpenCV's 4-path full SGM"))},
        "min_agree": {"description": "Slaves that must agree for a master pixel to be kept"},
        "tol_px": {"description": "Agreement tolerance (disparity pixels)"},
        "outlier_ratio": {"description": "A point is isolated when its mean distance to its neighbours "
                                                     "exceeds theirs by this factor"},
    },
    "surface": {
        "cell": {"description": "DSM and ortho cell (m, 0 = nadir GSD)"},
        "pit_size_m": {"description": "Enclosed DSM pits narrower than this are blunders (m, 0 = keep)"},
        "pit_depth": {"description": "Depth below their surroundings that makes a pit (m)"},
        "dsm_facade_nz": {"description": "Points whose normal is closer to horizontal than "
                                                             "this (|n_z|) are facade points, left out of the DSM"},
        "dsm_roof_hole_sides": {"description": "A DSM hole with roof on this many of its four "
                                                                   "sides is filled as roof (5 = never)"},
        "dsm_wall_step": {"description": "A DSM cell this far (m) below one neighbour and above the "
                                                     "opposite one lies on a wall and takes the nearer side (0 = off)"},
        "se_size": {"description": "DTM structuring element (m)"},
        "threshold": {"description": "Points within this of the opened surface are ground (m)"},
        "high_vegetation_m": {"description": "Vegetation points this high above the DTM are LAS class 5 "
                                                         "(high vegetation), lower ones class 4 (m)"},
    },
}
"""Stage -> field -> extra property settings: ``min``, ``max``, ``description``, ``items``
(``(value, name, description)`` choices that make a string field an enum)."""

_options_cache: dict[str, tuple[tuple, dict[str, Any]]] = {}


def scene_root(scene) -> Path | None:
    """The scene's workspace folder (absolute), or None."""
    path = scene.oblique_city.workspace
    return Path(bpy.path.abspath(path)) if path else None


def stage_option_values(scene, stage: str) -> dict[str, Any]:
    """``[stages.<stage>]`` of the scene's ``project.toml`` (empty without a readable workspace), re-read only
    when the file changed."""
    root = scene_root(scene)
    if root is None:
        return {}
    try:
        st = (root / PROJECT_FILE).stat()
    except OSError:
        return {}
    key = (st.st_mtime_ns, st.st_size, st.st_ino)
    cached = _options_cache.get(str(root))
    if cached is None or cached[0] != key:
        try:
            options = Workspace.open(root).project.get("stages", {})
        except CityError:
            options = {}
        cached = _options_cache[str(root)] = (key, options)
    return dict(cached[1].get(stage, {}))


def set_stage_option(scene, stage: str, name: str, value: Any) -> None:
    """Write one option into ``[stages.<stage>]`` of the scene's ``project.toml`` (checked by the stage's
    ``make_config``); nothing is written without a workspace."""
    root = scene_root(scene)
    if root is None:
        return
    ws = Workspace.open(root)
    ws.update_stage_options(stage, {name: value}, PROJECT_FILE)
    ws.save_project()
    _options_cache.pop(str(root), None)


def _option_property(stage: str, field: dataclasses.Field, default: Any) -> Any:
    """A property with get/set callbacks over one field of a stage's config, or None for a type the panel does
    not edit (tuples without ``items``, None defaults: those stay in ``project.toml``). A tuple with ``items`` is
    a set of choices (toggle buttons), written as a list."""
    hints = OPTION_HINTS.get(stage, {}).get(field.name, {})
    common = {"name": field.name.replace("_", " ").title(),
              "description": hints.get("description", f"[stages.{stage}] {field.name} in project.toml")}

    def value(scene) -> Any:
        v = stage_option_values(scene, stage).get(field.name, default)
        return v if isinstance(v, type(default)) or (isinstance(default, float) and isinstance(v, int)) else default

    if "items" in hints and isinstance(default, tuple):
        choices = [v for v, _, _ in hints["items"]]

        def get_flags(self) -> int:
            v = stage_option_values(self.id_data, stage).get(field.name, default)
            chosen = v if isinstance(v, (list, tuple)) else default
            return sum(1 << i for i, x in enumerate(choices) if x in chosen)

        return EnumProperty(items=[(v, n, d, 1 << i) for i, (v, n, d) in enumerate(hints["items"])],
                            options={"ENUM_FLAG"}, **common, get=get_flags,
                            set=lambda self, m: set_stage_option(self.id_data, stage, field.name,
                                                                 [x for i, x in enumerate(choices) if m >> i & 1]))
    if "items" in hints:
        values = [v for v, _, _ in hints["items"]]
        items = [(v or "AUTO", n, d, i) for i, (v, n, d) in enumerate(hints["items"])]

        def get_choice(self) -> int:
            v = value(self.id_data)
            return values.index(v) if v in values else 0

        return EnumProperty(items=items, **common, get=get_choice,
                            set=lambda self, i: set_stage_option(self.id_data, stage, field.name, values[i]))
    rule = get_stage(stage).config.RULES.get(field.name)
    bounds = {"min": rule.lo, "max": rule.hi} if isinstance(rule, Range) else {}  # the stage's own rule
    limits = {k: v for k, v in bounds.items() if math.isfinite(v)}
    if isinstance(default, bool):
        return BoolProperty(**common, get=lambda self: bool(value(self.id_data)),
                            set=lambda self, v: set_stage_option(self.id_data, stage, field.name, bool(v)))
    if isinstance(default, int):
        return IntProperty(**common, **{k: int(v) for k, v in limits.items()},
                           get=lambda self: int(value(self.id_data)),
                           set=lambda self, v: set_stage_option(self.id_data, stage, field.name, int(v)))
    if isinstance(default, float):  # Blender floats are single precision: 7 digits, so 2.7 stays 2.7 in the file
        return FloatProperty(**common, **limits, get=lambda self: float(value(self.id_data)),
                             set=lambda self, v: set_stage_option(self.id_data, stage, field.name,
                                                                  float(f"{v:.7g}")))
    if isinstance(default, str):
        return StringProperty(**common, get=lambda self: str(value(self.id_data)),
                              set=lambda self, v: set_stage_option(self.id_data, stage, field.name, str(v)))
    return None


def stage_options_group(stage: str) -> type:
    """A PropertyGroup with one property per editable field of the stage's config dataclass."""
    config = get_stage(stage).config
    defaults = config()
    props = {f.name: _option_property(stage, f, getattr(defaults, f.name)) for f in dataclasses.fields(config)}
    props = {k: v for k, v in props.items() if v is not None}
    ident = "CityOptions_" + stage
    return type(ident, (bpy.types.PropertyGroup,), {"__annotations__": props, "__doc__": f"Options of {stage}"})


def option_groups() -> dict[str, type]:
    """Stage -> its options PropertyGroup, for the stages of :data:`OPTION_STAGES` whose module imports (a stage
    whose dependencies are missing cannot run either: it gets no options, and the add-on still registers)."""
    groups = {}
    for stage in OPTION_STAGES:
        try:
            groups[stage] = stage_options_group(stage)
        except (CityError, ImportError):
            continue
    return groups


STAGE_OPTION_GROUPS: dict[str, type] = option_groups()
"""Stage -> its generated options PropertyGroup."""


def option_fields(stage: str) -> list[str]:
    """The fields of a stage's config that its panel edits, in the dataclass's order (none for a stage without
    options in the panel)."""
    return list(STAGE_OPTION_GROUPS[stage].__annotations__) if stage in STAGE_OPTION_GROUPS else []

CityStageOptions = type("CityStageOptions", (bpy.types.PropertyGroup,),
                        {"__annotations__": {stage: PointerProperty(type=cls)
                                             for stage, cls in STAGE_OPTION_GROUPS.items()},
                         "__doc__": "One group of options per stage of STAGE_OPTION_GROUPS"})


class CityBuildingItem(bpy.types.PropertyGroup):
    """One building of the Buildings panel's list; ``name`` is the building id (the list filters on it)."""

    path: StringProperty(name="Path", description="Reconstruction path: 2d or volumetric (empty: failed)")
    closed: BoolProperty(name="Closed", description="The model is a closed solid")
    failed: BoolProperty(name="Failed", description="The reconstruction failed (status holds the reason)")
    status: StringProperty(name="Status", description="closed solid, open: <problem> or failed: <reason>")
    seconds: FloatProperty(name="Seconds", description="Reconstruction time")
    surfaces: IntProperty(name="Surfaces", description="Number of surfaces of the model")
    dormers: IntProperty(name="Dormers", description="Dormers modelled on the building's roofs")
    roof_type: StringProperty(name="Roof Type", description="horizontal, multiple horizontal or slanted")
    height_70p: FloatProperty(name="Height (70 %)", description="70th percentile roof height above the ground "
                                                                "(the LoD 1.2 block's height), m")
    volume: FloatProperty(name="Volume", description="Volume of the LoD2 solid, m^3")


def _select_active_building(self, context) -> None:
    """Update of ``building_index``: select (and in a 3D viewport frame) the active building's object."""
    if 0 <= self.building_index < len(self.building_list):
        select_building(context, self.id_data, self.building_list[self.building_index].name)


class CitySceneSettings(bpy.types.PropertyGroup):
    workspace: StringProperty(name="Workspace", subtype="DIR_PATH",
                              description="Oblique City workspace folder of this scene")
    undistort_backgrounds: BoolProperty(
        name="Undistort Backgrounds", default=True,
        description="When looking through an image, show it resampled to Blender's distortion-free camera")
    force: BoolProperty(name="Force", default=False, description="Run stages again even if they are up to date")
    show_ground_points: BoolProperty(
        name="Show Ground Points", default=True,
        description="Draw the ground points' predicted and measured positions over the image looked through")
    measure_refine: BoolProperty(
        name="Fit Target", default=True,
        description="A ground point clicked in an image is taken at the centre of its target fitted near the click "
                    "(off: where the click is)")
    stage_options: PointerProperty(type=CityStageOptions)
    building_list: CollectionProperty(type=CityBuildingItem)
    building_index: IntProperty(name="Active Building", default=-1, update=_select_active_building)


class CityJobState(bpy.types.PropertyGroup):
    running: BoolProperty(name="Running", default=False)
    stage: StringProperty(name="Stage")
    fraction: FloatProperty(name="Progress", min=0.0, max=1.0, subtype="FACTOR")
    message: StringProperty(name="Message")
    status: StringProperty(name="Status", description="How the last job ended: done, failed or cancelled")


def preferences(context) -> tuple[str, ExecutorSettings]:
    """Job mode and executor settings from the preferences (defaults when the add-on is registered by hand, as
    scripts and tests with bpy from PyPI do, rather than enabled as an extension)."""
    addon = context.preferences.addons.get(ROOT_PACKAGE)
    if addon is None or addon.preferences is None:
        return "subprocess", ExecutorSettings()
    p = addon.preferences
    return p.job_mode, ExecutorSettings(p.executor, p.workers, p.scheduler)


CLASSES = (CityPreferences, *STAGE_OPTION_GROUPS.values(), CityStageOptions, CityBuildingItem, CitySceneSettings,
           CityJobState)


def attach() -> None:
    """Add the pointer properties (after the classes are registered)."""
    bpy.types.Scene.oblique_city = PointerProperty(type=CitySceneSettings)
    bpy.types.WindowManager.oblique_city_job = PointerProperty(type=CityJobState)


def detach() -> None:
    del bpy.types.WindowManager.oblique_city_job
    del bpy.types.Scene.oblique_city
