"""bench/sparse_fit.py (scripts/diagnostics/sparse_depth_fit.py): a run's depth against the sparse points."""

import math

import torch

from frugalnerf_ns.bench.sparse_fit import agreement_by_depth, depth_agreement
from frugalnerf_ns.model.losses import inverse_depth_loss, inverse_depth_term


def test_agreement_counts_the_points_off_by_more_than_ten_percent_and_reports_the_loss_term():
    target = torch.tensor([1.0, 2.0, 4.0, 10.0, 50.0])
    rendered = torch.tensor([1.0, 2.1, 3.0, 10.5, 100.0])  # off by 0, 5, 25, 5, 100 %
    summary = depth_agreement(rendered, target)
    assert summary["observations"] == 5
    assert math.isclose(summary["median_relative"], 0.05, rel_tol=1e-5)
    assert math.isclose(summary["above_10_percent"], 0.4)
    expected = ((1 / rendered - 1 / target) ** 2).mean()
    assert math.isclose(summary["mean_inverse_depth_term"], float(expected), rel_tol=1e-5)
    assert depth_agreement(torch.zeros(0), torch.zeros(0)) == {"observations": 0}


def test_depth_bands_split_by_the_points_depth_and_their_term_shares_add_up():
    target = torch.tensor([50.0, 1.0, 40.0, 2.0])
    rendered = torch.tensor([100.0, 1.1, 40.0, 2.0])  # the far point doubled, the nearest off by 10 %
    bands = agreement_by_depth(rendered, target, bins=2)
    assert [(b["depth_from"], b["depth_to"]) for b in bands] == [(1.0, 2.0), (40.0, 50.0)]
    assert [b["observations"] for b in bands] == [2, 2]
    assert math.isclose(sum(b["share_of_term"] for b in bands), 1.0, rel_tol=1e-5)
    # A 10 % error on a point at depth 1 weighs more in inverse depth than doubling a point at 50.
    near_term = (1 / 1.1 - 1.0) ** 2
    far_term = (1 / 100 - 1 / 50) ** 2
    assert math.isclose(bands[0]["share_of_term"], near_term / (near_term + far_term), rel_tol=1e-4)
    assert bands[0]["share_of_term"] > bands[1]["share_of_term"]
    assert math.isclose(bands[1]["above_10_percent"], 0.5)
    assert math.isclose(bands[0]["mean_inverse_depth_term"] * 2 + bands[1]["mean_inverse_depth_term"] * 2,
                        float(inverse_depth_loss(rendered, target)) * 4, rel_tol=1e-5)


def test_the_per_observation_term_averages_to_the_training_loss():
    rendered = torch.tensor([0.0, 0.5, 3.0, 80.0])  # an empty ray (depth 0) too: both clamp it
    target = torch.tensor([1.0, 0.4, 3.3, 60.0])
    assert math.isclose(float(inverse_depth_term(rendered, target).mean()), float(inverse_depth_loss(rendered, target)), rel_tol=1e-6)
