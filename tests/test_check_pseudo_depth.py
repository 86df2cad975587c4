"""scripts/check_pseudo_depth.py: COLMAP's binary points read back, and the pick-vs-truth summary by hand."""

import struct

import numpy as np
import torch

from tests.helpers import load_script


def test_points3d_bin_round_trip(tmp_path):
    check = load_script("check_pseudo_depth")
    points = [(1.5, -2.0, 3.25), (0.0, 4.0, -1.0)]
    with open(tmp_path / "points3D.bin", "wb") as f:
        f.write(struct.pack("<Q", len(points)))
        for n, xyz in enumerate(points):
            track = [(1, 7), (2, 9), (5, 0)][: n + 1]
            f.write(struct.pack("<Qddd", n + 1, *xyz) + bytes([10, 20, 30]) + struct.pack("<d", 0.5))
            f.write(struct.pack("<Q", len(track)) + b"".join(struct.pack("<ii", *t) for t in track))
    assert np.array_equal(check.read_points3d_bin(tmp_path / "points3D.bin"), np.array(points))


def test_summary_counts_closest_and_picked_scales():
    check = load_script("check_pseudo_depth")
    truth = torch.tensor([1.0, 2.0, 4.0, 1.0])
    depths = torch.tensor([[1.1, 2.0, 3.0, 1.5],   # full scale: errors 0.1, 0, 0.25, 0.5
                           [1.0, 2.4, 4.0, 1.2]])  # scale 1:   errors 0, 0.2, 0, 0.2
    chosen = torch.tensor([1, 0, 0, -1])  # right, right, wrong, left out
    r = check.summarise(depths, truth, chosen)
    assert r["closest_fraction_per_scale"] == [0.25, 0.75]
    assert r["picked_fraction_per_scale"] == [0.5, 0.25] and r["left_out_fraction"] == 0.25
    assert abs(r["pick_is_closest"] - 2 / 3) < 1e-6
    assert abs(r["pseudo_closer_than_full"] - 1 / 3) < 1e-6  # only the first ray's pick beats the full scale
