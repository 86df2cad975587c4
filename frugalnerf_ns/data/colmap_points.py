"""COLMAP's sparse model as a reader of its points alone: the XYZ of every point in ``sparse/0/points3D.bin``
(COLMAP's binary format), without pycolmap and without COLMAP. Colour, reprojection error and tracks are read
past. ``scripts/diagnostics/check_pseudo_depth.py`` checks rendered and pseudo depths against these points
of an LLFF capture (COLMAP's world frame, before any dataparser's transform or scale).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np


def read_points3d_bin(path: Path) -> np.ndarray:
    """XYZ of every point in a COLMAP ``points3D.bin`` (id, xyz, rgb, error, track)."""
    with open(path, "rb") as f:
        (count,) = struct.unpack("<Q", f.read(8))
        points = np.empty((count, 3))
        for n in range(count):
            _, x, y, z = struct.unpack("<Qddd", f.read(32))
            f.read(3 + 8)  # rgb, reprojection error
            (track,) = struct.unpack("<Q", f.read(8))
            f.read(8 * track)  # (image id, point2D index) int32 pairs
            points[n] = (x, y, z)
    return points
