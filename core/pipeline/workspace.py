"""The workspace: a project folder with ``project.toml``, ``block/``, one folder per stage and ``state.json``."""

from __future__ import annotations

import dataclasses
import json
import tomllib
from pathlib import Path
from typing import Any

from ..errors import WorkspaceError
from .atomic import write_json, write_text

PROJECT_FILE = "project.toml"
STATE_FILE = "state.json"
BLOCK_FILE = "block/block.json"
ADJUSTED_BLOCK_FILE = "aerotri/block.json"


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: dict[str, Any]) -> str:
    """A small TOML writer for the project file: scalars, lists and nested tables (None values are skipped)."""
    lines: list[str] = []

    def table(prefix: str, d: dict[str, Any]) -> None:
        scalars = {k: v for k, v in d.items() if not isinstance(v, dict) and v is not None}
        subs = {k: v for k, v in d.items() if isinstance(v, dict)}
        if prefix and (scalars or not subs):
            lines.append(f"\n[{prefix}]")
        for k, v in scalars.items():
            lines.append(f"{k} = {_toml_value(v)}")
        for k, v in subs.items():
            table(f"{prefix}.{k}" if prefix else k, v)

    table("", doc)
    return "\n".join(lines).lstrip("\n") + "\n"


class Workspace:
    """A project folder. Create with :meth:`create`, open with :meth:`open`."""

    def __init__(self, root: str | Path, project: dict[str, Any]) -> None:
        self.root = Path(root).resolve()
        self.project = project

    @classmethod
    def create(cls, root: str | Path, crs: str, name: str | None = None, exist_ok: bool = False) -> Workspace:
        """Make a new workspace folder with a ``project.toml``."""
        from ..geometry.crs import normalize_crs

        root = Path(root)
        if (root / PROJECT_FILE).exists() and not exist_ok:
            raise WorkspaceError(f"{root}: a workspace already exists here")
        root.mkdir(parents=True, exist_ok=True)
        project = {"project": {"name": name or root.resolve().name, "crs": normalize_crs(crs)}, "stages": {}}
        ws = cls(root, project)
        ws.save_project()
        return ws

    @classmethod
    def open(cls, root: str | Path) -> Workspace:
        root = Path(root)
        path = root / PROJECT_FILE
        if not path.exists():
            raise WorkspaceError(f"{root}: not a workspace (no {PROJECT_FILE}); create one with 'oblique-city new'")
        try:
            project = tomllib.loads(path.read_text(encoding="utf-8"))
        except tomllib.TOMLDecodeError as e:
            raise WorkspaceError(f"{path}: {e}") from None
        if "project" not in project or "crs" not in project["project"]:
            raise WorkspaceError(f"{path}: missing [project] crs")
        project.setdefault("stages", {})
        return cls(root, project)

    # --- paths -------------------------------------------------------------------------------------------
    def path(self, *parts: str) -> Path:
        """Absolute path inside the workspace."""
        return self.root.joinpath(*parts)

    def stage_dir(self, name: str) -> Path:
        """The folder of a stage's artefacts (created)."""
        p = self.root / name
        p.mkdir(parents=True, exist_ok=True)
        return p

    @property
    def crs(self) -> str:
        return self.project["project"]["crs"]

    # --- project and configs -----------------------------------------------------------------------------
    def save_project(self) -> None:
        write_text(self.root / PROJECT_FILE, dump_toml(self.project))

    def stage_options(self, name: str) -> dict[str, Any]:
        return dict(self.project.get("stages", {}).get(name, {}))

    def update_stage_options(self, name: str, values: dict[str, Any], source: str) -> None:
        """Set options of stage ``name`` in memory once its config takes them with the options already set
        (:class:`ConfigError` naming ``source`` otherwise: an unknown stage or option, a wrong type or value);
        :meth:`save_project` writes them."""
        from .registry import get_stage

        merged = {**self.stage_options(name), **values}
        get_stage(name).make_config(merged, source)
        self.project.setdefault("stages", {})[name] = merged

    def set_stage_config(self, name: str, cfg: Any) -> None:
        """Store a stage's config dataclass in ``project.toml``."""
        values = {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(cfg).items()}
        self.project.setdefault("stages", {})[name] = values
        self.save_project()

    # --- block -------------------------------------------------------------------------------------------
    def has_block(self) -> bool:
        return (self.root / BLOCK_FILE).exists()

    def save_block(self, block, path: str = BLOCK_FILE) -> None:
        """Write a block (the imported one by default) atomically."""
        from ..io.native import write_block

        write_block(block, self.root / path)

    def load_block(self, adjusted: bool = True):
        """The block: the adjusted one from aerial triangulation when it exists and ``adjusted``, else the
        imported one."""
        from ..io.native import read_block

        if adjusted and (self.root / ADJUSTED_BLOCK_FILE).exists():
            return read_block(self.root / ADJUSTED_BLOCK_FILE)
        if not self.has_block():
            raise WorkspaceError(f"{self.root}: no block imported yet (run 'oblique-city import')")
        return read_block(self.root / BLOCK_FILE)

    # --- state -------------------------------------------------------------------------------------------
    def read_state(self) -> dict[str, Any]:
        p = self.root / STATE_FILE
        if not p.exists():
            return {}
        try:
            return json.loads(p.read_text(encoding="utf-8"))
        except json.JSONDecodeError as e:
            raise WorkspaceError(f"{p}: corrupt state file ({e.msg}, line {e.lineno})") from None

    def write_state(self, state: dict[str, Any]) -> None:
        write_json(self.root / STATE_FILE, state)
