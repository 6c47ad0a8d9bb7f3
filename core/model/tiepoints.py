"""Tie points: multi-ray image observations of unknown ground points, stored as flat numpy arrays."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(eq=False)
class TiePoints:
    """Tracks and their observations.

    Attributes
    ----------
    xyz : (n, 3) float64 ground coordinates of the n tracks (NaN until intersected)
    obs_track : (m,) int64 track index of each observation
    obs_image : (m,) int64 index into ``image_ids`` of each observation
    obs_uv : (m, 2) float64 pixel position (origin at the centre of the top-left pixel)
    image_ids : the image ids the ``obs_image`` indices refer to
    obs_blunder : (m,) bool, observations flagged as blunders (by the adjustment or, in simulations, truth)
    colour : (n, 3) uint8 or None
    """

    xyz: np.ndarray
    obs_track: np.ndarray
    obs_image: np.ndarray
    obs_uv: np.ndarray
    image_ids: list[str]
    obs_blunder: np.ndarray | None = None
    colour: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.xyz = np.asarray(self.xyz, dtype=np.float64).reshape(-1, 3)
        self.obs_track = np.asarray(self.obs_track, dtype=np.int64)
        self.obs_image = np.asarray(self.obs_image, dtype=np.int64)
        self.obs_uv = np.asarray(self.obs_uv, dtype=np.float64).reshape(-1, 2)
        if self.obs_blunder is None:
            self.obs_blunder = np.zeros(len(self.obs_track), dtype=bool)

    @property
    def n_tracks(self) -> int:
        return len(self.xyz)

    @property
    def n_obs(self) -> int:
        return len(self.obs_track)

    def ray_counts(self) -> np.ndarray:
        """Number of observations per track, (n,) int64."""
        return np.bincount(self.obs_track, minlength=self.n_tracks)

    def save(self, path: str) -> None:
        """Write to a ``.npz`` file atomically."""
        from ..pipeline.atomic import atomic_path

        arrays = {
            "xyz": self.xyz, "obs_track": self.obs_track, "obs_image": self.obs_image, "obs_uv": self.obs_uv,
            "obs_blunder": self.obs_blunder, "image_ids": np.array(self.image_ids, dtype=np.str_),
        }
        if self.colour is not None:
            arrays["colour"] = self.colour
        for k, v in self.extra.items():
            arrays["extra_" + k] = v
        with atomic_path(path) as tmp, open(tmp, "wb") as f:
            np.savez_compressed(f, **arrays)

    @classmethod
    def load(cls, path: str) -> TiePoints:
        """Read a file written by :meth:`save`; pickled content is refused (never unpickle workspace files)."""
        from ..errors import WorkspaceError

        try:
            with np.load(path, allow_pickle=False) as z:
                extra = {k[6:]: z[k] for k in z.files if k.startswith("extra_")}
                return cls(
                    xyz=z["xyz"], obs_track=z["obs_track"], obs_image=z["obs_image"], obs_uv=z["obs_uv"],
                    image_ids=[str(s) for s in z["image_ids"]], obs_blunder=z["obs_blunder"],
                    colour=z["colour"] if "colour" in z.files else None, extra=extra,
                )
        except (OSError, ValueError, KeyError) as e:
            raise WorkspaceError(f"{path}: not a tie point file of this version ({e}); rerun the stage "
                                 "that wrote it") from None
