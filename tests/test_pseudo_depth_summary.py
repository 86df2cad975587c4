"""scoring/pseudo_depth.py: the pseudo-depth scale picks against the true depths, summarised by hand."""

import torch

from frugalnerf_ns.scoring.pseudo_depth import summarise


def test_summary_counts_closest_and_picked_scales():
    truth = torch.tensor([1.0, 2.0, 4.0, 1.0])
    depths = torch.tensor([[1.1, 2.0, 3.0, 1.5],   # full scale: errors 0.1, 0, 0.25, 0.5
                           [1.0, 2.4, 4.0, 1.2]])  # scale 1:   errors 0, 0.2, 0, 0.2
    chosen = torch.tensor([1, 0, 0, -1])  # right, right, wrong, left out
    r = summarise(depths, truth, chosen)
    assert r["closest_fraction_per_scale"] == [0.25, 0.75]
    assert r["picked_fraction_per_scale"] == [0.5, 0.25] and r["left_out_fraction"] == 0.25
    assert abs(r["pick_is_closest"] - 2 / 3) < 1e-6
    assert abs(r["pseudo_closer_than_full"] - 1 / 3) < 1e-6  # only the first ray's pick beats the full scale
