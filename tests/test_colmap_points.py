"""data/colmap_points.py: COLMAP's binary points (``points3D.bin``) read back."""

import struct

import numpy as np

from frugalnerf_ns.data.colmap_points import read_points3d_bin


def test_points3d_bin_round_trip(tmp_path):
    points = [(1.5, -2.0, 3.25), (0.0, 4.0, -1.0)]
    with open(tmp_path / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for n, xyz in enumerate(points):
            track = [(1, 7), (2, 9), (5, 0)][: n + 1]
            f.write(struct.pack("<Qddd", n + 1, *xyz) + bytes([10, 20, 30]) + struct.pack("<d", 0.5))
            f.write(struct.pack("<Q", len(track)) + b"".join(struct.pack("<ii", *t) for t in track))
    assert np.array_equal(read_points3d_bin(tmp_path / "points3D.bin"), np.array(points))
