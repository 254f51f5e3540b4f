"""The bin the parts lie in: an open box of the world frame, where a cell knows it.

A robot cell's bin stands where the integrator put it: its pose in the robot's base frame is
calibrated like the cameras'. Where it is known, a part's centre cannot lie outside it, least
of all under its floor. In a pile of one part type, two detections of different parts (or of
none) can meet in 3D far from any part: on the tuning piles a third of the tracks more than
0.3 d off their part lay under the bin's floor, up to half a metre under it, and none of the
right ones (docs/lab/2026-12-08-bin-floor-ghosts.md). Such a track is published tentative
(:class:`~estimator.tracker.config.TrackerConfig`'s ``bin``); next-best-view uses the same
region for the walls a line of sight must clear.

Frames: ``T_world_bin`` (4, 4) puts the bin's inner floor centre at its origin, z up out of
the bin; the inner floor spans ``size`` (x, y) metres, the walls rise ``wall_height`` above it.
The region is open upwards: a pile may rise above the rim.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from posefuse.estimator.core.geometry import invert


@dataclass(frozen=True, eq=False)
class BinRegion:
    """An open box the parts lie in: inner floor ``size`` (x, y) metres, walls ``wall_height``
    high, its floor's centre at the origin of ``T_world_bin`` (4, 4) with z up."""

    size: tuple[float, float] = (0.42, 0.32)
    wall_height: float = 0.08
    T_world_bin: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        size = tuple(float(s) for s in self.size)
        wall_height = float(self.wall_height)
        if (
            len(size) != 2
            or not all(math.isfinite(s) and s > 0 for s in size)
            or not (math.isfinite(wall_height) and wall_height >= 0)
        ):
            raise ValueError(
                f"bin region: size must be two positive widths and wall_height at least 0, "
                f"got size {self.size} and wall_height {self.wall_height}"
            )
        T = np.asarray(self.T_world_bin, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise ValueError(f"bin region: T_world_bin must be a finite (4, 4) pose, got {T}")
        R = T[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) <= 0:
            raise ValueError("bin region: T_world_bin's rotation is not a rotation matrix")
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise ValueError("bin region: T_world_bin's last row must be 0 0 0 1")
        object.__setattr__(self, "size", size)
        object.__setattr__(self, "wall_height", wall_height)
        object.__setattr__(self, "T_world_bin", T)

    def distance_outside(self, p_world: np.ndarray) -> np.ndarray:
        """How far each point lies outside the region (0 inside): beyond a wall's inner face
        or under the floor, metres; the top is open.

        Args:
            p_world: (..., 3) points in the world frame.
        Returns:
            (...) distances, the largest of the per-axis excesses (the box's L-infinity
            distance, which a point must cross at least).
        """
        p = np.asarray(p_world, float)
        T_bin_world = invert(self.T_world_bin)
        q = p @ T_bin_world[:3, :3].T + T_bin_world[:3, 3]
        half = 0.5 * np.asarray(self.size)
        over = np.stack(
            [np.abs(q[..., 0]) - half[0], np.abs(q[..., 1]) - half[1], -q[..., 2]], axis=-1
        )
        return np.maximum(over.max(axis=-1), 0.0)

    def to_json(self) -> dict:
        """The region as JSON values (``from_json`` reads them back)."""
        return {
            "size": list(self.size),
            "wall_height": self.wall_height,
            "T_world_bin": self.T_world_bin.tolist(),
        }

    @classmethod
    def from_json(cls, value) -> BinRegion:
        """A region from :meth:`to_json`'s values; ValueError naming what is wrong."""
        if not isinstance(value, dict):
            raise ValueError(
                f"a bin region is an object with size, wall_height and T_world_bin, "
                f"got {type(value).__name__}"
            )
        unknown = sorted(set(value) - {"size", "wall_height", "T_world_bin"})
        if unknown:
            raise ValueError(
                f"a bin region has no {unknown}: it has size, wall_height and T_world_bin"
            )
        missing = [k for k in ("size", "wall_height") if k not in value]
        if missing:
            raise ValueError(
                f"a bin region needs {missing} (T_world_bin: the identity if left out)"
            )
        try:
            return cls(
                tuple(value["size"]),
                value["wall_height"],
                np.array(value.get("T_world_bin", np.eye(4)), float),
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(str(exc)) from None
