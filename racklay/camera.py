"""The pinhole camera, one for the whole project: WareSynth renders through it
(`racklay.synth.scene.Camera` adds the image size and lens distortion) and the annotator recovers
it from a rack's four corners (`annotate.geometry.Camera` adds whether the photo fixed the focal
length).

A world point X (metres; the frame is the caller's: the warehouse for WareSynth, the rack for the
annotator) is seen at pixel x ~ K (R X + t), pixel centres at integer + 0.5.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PinholeCamera:
    K: np.ndarray          # 3 x 3 intrinsics
    R: np.ndarray          # 3 x 3 world -> camera rotation
    t: np.ndarray          # 3, world -> camera translation

    @property
    def center(self) -> np.ndarray:
        """The camera centre in the world frame."""
        return -self.R.T @ self.t

    def to_cam(self, pts) -> np.ndarray:
        """World points (N, 3) -> camera coordinates (N, 3)."""
        return np.asarray(pts, dtype=np.float64).reshape(-1, 3) @ self.R.T + self.t

    def project_z(self, pts) -> tuple[np.ndarray, np.ndarray]:
        """World points (N, 3) -> (pixel coordinates (N, 2), depth along the optical axis (N,));
        points at depth ~0 are divided by 1e-9, not 0 (check z before trusting their pixels)."""
        pc = self.to_cam(pts)
        z = pc[:, 2]
        uv = (pc @ self.K.T)[:, :2] / np.where(np.abs(z) < 1e-9, 1e-9, z)[:, None]
        return uv, z

    def project(self, pts) -> np.ndarray:
        """World points (N, 3) -> pixel coordinates (N, 2)."""
        return self.project_z(pts)[0]

    def ray(self, pt) -> tuple[np.ndarray, np.ndarray]:
        """(camera centre, direction) in the world frame of the ray through pixel `pt`."""
        d = self.R.T @ np.linalg.solve(self.K, [float(pt[0]), float(pt[1]), 1.0])
        return self.center, d
