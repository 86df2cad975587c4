"""Candidate viewpoints, their descriptions and the start-up coverage line (pure torch, no nerfstudio)."""

from __future__ import annotations

import math

import pytest
import torch

from frugalnerf_ns.geometry.camera_conventions import look_at_poses
from frugalnerf_ns.geometry.viewpoints import (
    angle_difference,
    candidate_poses,
    coverage_line,
    describe,
    largest_gap_pose,
    neighbour_gaps,
    separations,
    subject_frame,
)

UP = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
TARGET = torch.tensor([0.3, -0.2, 0.5], dtype=torch.float64)


def ring(azimuths_deg, distance=3.0, elevation_deg=20.0):
    """Cameras around TARGET at the given azimuths (degrees, counter-clockwise about +z), looking at it."""
    az = torch.deg2rad(torch.tensor(azimuths_deg, dtype=torch.float64))
    el = math.radians(elevation_deg)
    offsets = torch.stack([az.cos() * math.cos(el), az.sin() * math.cos(el), torch.full_like(az, math.sin(el))], -1)
    return look_at_poses(TARGET + distance * offsets, TARGET, UP)


def test_the_subject_frame_measures_azimuth_elevation_and_distance_of_a_known_ring():
    cameras = ring([10.0, 40.0, 70.0], distance=3.0, elevation_deg=20.0)
    frame = subject_frame(cameras)
    assert torch.allclose(frame.focus, TARGET, atol=1e-6)
    assert torch.allclose(frame.azimuths(cameras[:, :3, 3]), torch.tensor([0.0, 30.0, 60.0], dtype=torch.float64), atol=1e-6)
    assert torch.allclose(frame.elevations(cameras[:, :3, 3]), torch.full((3,), 20.0, dtype=torch.float64), atol=1e-6)
    assert torch.allclose(frame.distances(cameras[:, :3, 3]), torch.full((3,), 3.0, dtype=torch.float64), atol=1e-6)
    back = frame.positions(torch.tensor([30.0]), torch.tensor([20.0]), torch.tensor([3.0]))
    assert torch.allclose(back[0], cameras[1, :3, 3], atol=1e-6)


def test_neighbour_gaps_go_round_the_circle_and_add_up_to_360():
    gaps = neighbour_gaps([350.0, 20.0, 100.0])
    assert sum(g for g, _, _ in gaps) == pytest.approx(360.0)
    assert max(gaps) == pytest.approx((250.0, 2, 0))  # from 100 round to 350
    assert float(angle_difference(torch.tensor(10.0), torch.tensor(350.0))) == pytest.approx(20.0)


def test_ring_candidates_stand_at_the_photos_height_and_distance_and_look_at_the_subject():
    cameras = ring([0.0, 30.0, 60.0], distance=2.5, elevation_deg=15.0)
    candidates = candidate_poses(cameras, forward_facing=False, step_degrees=15.0)
    assert candidates.layout == "ring" and len(candidates.camera_to_worlds) == 24
    frame = subject_frame(cameras)
    centres = candidates.camera_to_worlds[:, :3, 3].double()
    assert torch.allclose(frame.distances(centres), torch.full((24,), 2.5, dtype=torch.float64), atol=1e-4)
    assert torch.allclose(frame.elevations(centres), torch.full((24,), 15.0, dtype=torch.float64), atol=1e-3)
    looking = -candidates.camera_to_worlds[:, :3, 2].double()
    towards = torch.nn.functional.normalize(TARGET - centres, dim=-1)
    assert torch.allclose((looking * towards).sum(-1), torch.ones(24, dtype=torch.float64), atol=1e-5)
    spacing = angle_difference(frame.azimuths(centres[1:]), frame.azimuths(centres[:-1]))
    assert torch.allclose(spacing, torch.full((23,), 15.0, dtype=torch.float64), atol=1e-3)


def test_plane_candidates_of_forward_facing_photos_lie_in_their_plane_and_look_ahead():
    positions = torch.tensor([[-0.2, 0.0, 0.0], [0.2, 0.05, 0.0]], dtype=torch.float64)
    cameras = look_at_poses(positions, torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64),
                            torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    candidates = candidate_poses(cameras, forward_facing=True, look_at_depth=4.0, plane_steps=5)
    assert candidates.layout == "plane" and len(candidates.camera_to_worlds) == 25
    centres = candidates.camera_to_worlds[:, :3, 3].double()
    assert centres[:, 2].abs().max() < 0.02  # the cameras' plane (z ~ 0)
    assert float(centres[:, 0].max()) >= 0.4 - 1e-6  # twice the photos' extent
    assert (candidates.camera_to_worlds[:, 2, 2] > 0.98).all()  # all look down -z (their back axis is +z), at the scene


def test_descriptions_name_the_photos_around_the_candidate_and_the_side_it_lies_on():
    cameras = ring([0.0, 60.0])
    names = ["a.jpg", "b.jpg"]
    between = ring([20.0])[0]
    text = describe(between, cameras, names, forward_facing=False)
    assert text.startswith("between photos 1 and 2") and "20 degrees" in text
    # Counter-clockwise about up is to the right as seen from a photo facing the subject.
    assert "right of photo 1 (a.jpg)" in text
    assert "same height" in text and "1.0x its distance" in text
    left = describe(ring([-25.0], distance=3.6, elevation_deg=35.0)[0], cameras, names, forward_facing=False)
    assert "25 degrees left of photo 1" in left and "15 degrees higher" in left and "1.2x" in left
    assert "far side" in left  # outside the 60-degree span, in the 300-degree gap


def test_the_largest_gap_pose_lies_in_the_middle_of_the_largest_gap():
    cameras = ring([0.0, 30.0, 90.0])
    pose, gap = largest_gap_pose(cameras)
    assert gap == pytest.approx(270.0)
    frame = subject_frame(cameras)
    assert float(frame.azimuths(pose[None, :3, 3])[0]) == pytest.approx(-135.0, abs=1e-3)  # 90 + 135 = 225


def test_the_coverage_line_judges_the_gaps_between_neighbouring_photos():
    good = coverage_line(ring([0.0, 14.0, 29.0]), ["1", "2", "3"], forward_facing=False, num_points=120)
    assert good.startswith("3 photos over 29 degrees around the subject, up to 15 degrees between neighbours: good")
    assert "120 points" in good
    wide = coverage_line(ring([0.0, 60.0, 120.0, 180.0]), ["1", "2", "3", "4"], forward_facing=False)
    assert "4 photos over 180 degrees" in wide and "60 degrees between neighbours" in wide
    assert "will be guessed" in wide and "helps most" in wide
    assert "a photo between photos 4 and 1, 90 degrees left of photo 1" in wide  # the middle of the 180-degree gap
    open_side = coverage_line(ring([0.0, 14.0, 29.0, 150.0]), ["1", "2", "3", "4"], forward_facing=False)
    assert "up to 121 degrees" in open_side and "far side from photos 4 and 1, 105 degrees right of photo 4" in open_side
    closed = coverage_line(ring([0.0, 20.0, 40.0, 60.0, 80.0, 100.0]), list("123456"), forward_facing=False)
    assert "good between them; the other side is guessed; a photo on the far side" in closed
    fair = coverage_line(ring([0.0, 40.0, 80.0]), ["1", "2", "3"], forward_facing=False)
    assert "fair" in fair
    single = coverage_line(ring([0.0]), ["1"], forward_facing=False)
    assert single.startswith("1 photo")


def test_the_coverage_line_of_forward_facing_photos_states_the_baseline():
    positions = torch.tensor([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0]], dtype=torch.float64)
    cameras = look_at_poses(positions, torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64),
                            torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))
    line = coverage_line(cameras, ["1", "2"], forward_facing=True)
    assert line.startswith("2 photos side by side") and "baseline 10% of the distance" in line


def test_separation_is_the_angle_to_the_nearest_photo_around_a_subject_and_the_distance_beside_forward_photos():
    cameras = ring([0.0, 60.0])
    far = separations(ring([210.0, 30.0, 0.0]), cameras, forward_facing=False)
    assert torch.allclose(far, torch.tensor([150.0 / 180.0, 30.0 / 180.0, 0.0], dtype=torch.float64), atol=1e-4)
    positions = torch.tensor([[-0.2, 0.0, 0.0], [0.2, 0.0, 0.0]], dtype=torch.float64)
    target = torch.tensor([0.0, 0.0, -4.0], dtype=torch.float64)
    y_up = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    photos = look_at_poses(positions, target, y_up)
    queries = look_at_poses(torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.0, 0.0], [2.0, 0.0, 0.0]], dtype=torch.float64), target, y_up)
    assert torch.allclose(separations(queries, photos, forward_facing=True),
                          torch.tensor([0.5, 0.0, 1.0], dtype=torch.float64), atol=1e-6)
