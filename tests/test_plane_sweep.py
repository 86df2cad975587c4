"""Plane-sweep stereo (geometry/plane_sweep.py): depths on a textured plane, the checks that drop pixels, the
banded sweep, and the points it adds to the sparse depth (data/sparse_points.py)."""

import dataclasses

import numpy as np
import torch

from frugalnerf_ns.data.sparse_points import (
    SparseDepth,
    TriangulationOptions,
    concatenate,
    triangulate_training_views,
    z_depth_range,
)
from frugalnerf_ns.data.training_points import cache_key
from frugalnerf_ns.geometry.plane_sweep import (
    StereoOptions,
    best_plane,
    plane_inverse_depths,
    left_right_check,
    pixel_rays,
    plane_sweep_depth,
    stereo_matches,
)
from frugalnerf_ns.geometry.reprojection import project_to_camera
from tests.photo_scene import texture
from tests.plane_scene import PLANE_Z, camera, intrinsics, render_plane

NEAR, FAR = 2.0, 4.0  # the plane lies ~3 units from both cameras
ROWS, COLUMNS = slice(60, 180), slice(80, 240)  # the middle of render_plane's 320x240 (a quarter of the sweep's time)


def plane_pair():
    """Two views of the textured plane, cropped to their middles: grey uint8 images, cameras, intrinsics."""
    c2w = torch.stack([camera((0.25, 0.1, 2.0)), camera((-0.25, -0.05, 2.1))])
    images = [render_plane(c, texture())[ROWS, COLUMNS] for c in c2w]
    k = intrinsics(2).clone()
    k[:, 2] -= COLUMNS.start
    k[:, 3] -= ROWS.start
    return images, c2w, k


def grey(image):
    return torch.from_numpy(image.astype(np.float32) / 255.0)  # render_plane draws grey levels


def test_the_matches_lie_on_the_textured_plane_and_on_both_pixels_rays():
    images, c2w, k = plane_pair()
    match = stereo_matches((grey(images[0]), grey(images[1])), c2w.float(), k.float(), NEAR, FAR)
    # The pair overlaps on most of the image: most textured pixels match.
    assert match.points.shape[0] >= 0.15 * images[0].size
    points = match.points.double()
    true_z = PLANE_Z - 0.2 * points[:, 0]
    n = points.shape[0]
    depth = project_to_camera(points, c2w[0].expand(n, 3, 4), k[:1].expand(n, 4)).depth
    rel = (points[:, 2] - true_z).abs() / depth
    assert float(rel.median()) < 0.003 and float(rel.quantile(0.99)) < 0.02
    # The point projects to the reference pixel and to the source pixel it reports.
    for view, pixels in ((0, match.reference_pixels), (1, match.source_pixels)):
        proj = project_to_camera(points, c2w[view].expand(n, 3, 4), k[view].expand(n, 4))
        assert torch.allclose(proj.pixels, pixels.double(), atol=2e-3)


def test_a_flat_image_matches_nowhere():
    images, c2w, k = plane_pair()
    flat = torch.full(images[0].shape[:2], 0.5)
    match = stereo_matches((flat, flat), c2w.float(), k.float(), NEAR, FAR)
    assert match.points.shape[0] == 0


def test_where_the_source_view_shows_something_else_nothing_matches():
    images, c2w, k = plane_pair()
    reference, source = grey(images[0]), grey(images[1]).clone()
    full = stereo_matches((reference, source), c2w.float(), k.float(), NEAR, FAR)
    # Another texture on the source's left half: the reference pixels that land there have no true match.
    other = grey(render_plane(c2w[1], texture(seed=7))[ROWS, COLUMNS])
    source[:, : source.shape[1] // 2] = other[:, : source.shape[1] // 2]
    cut = stereo_matches((reference, source), c2w.float(), k.float(), NEAR, FAR)
    landed_left = cut.source_pixels[:, 0] < source.shape[1] // 2 - 4
    assert float(landed_left.double().mean()) < 0.01
    right = full.source_pixels[:, 0] > source.shape[1] // 2 + 4
    assert cut.points.shape[0] >= 0.8 * int(right.sum())


def plane_depth(c2w, k, shape):
    """Each pixel's z-depth on the tilted plane z + 0.2 x = PLANE_Z."""
    rays, _ = pixel_rays(c2w, k, *shape)
    origin = c2w[:3, 3]
    return (PLANE_Z - origin[2] - 0.2 * origin[0]) / (rays[..., 2] + 0.2 * rays[..., 0])


def test_the_left_right_check_keeps_consistent_depths_and_drops_the_rest():
    images, c2w, k = plane_pair()
    shape = images[0].shape
    forward, backward = plane_depth(c2w[0], k[0], shape), plane_depth(c2w[1], k[1], shape)
    points, uv, source_uv, consistent = left_right_check(forward, backward, c2w, k, 1.0)
    landed = (source_uv[..., 0] >= 0) & (source_uv[..., 0] < shape[1]) & (source_uv[..., 1] >= 0) & (source_uv[..., 1] < shape[0])
    assert torch.equal(consistent, landed) and float(landed.double().mean()) > 0.7
    n = int(consistent.sum())
    proj = project_to_camera(points[consistent], c2w[1].expand(n, 3, 4), k[1].expand(n, 4))
    assert torch.allclose(proj.pixels, source_uv[consistent], atol=1e-9)
    # A source depth 10 % off on the left half carries its pixels back far from where they came from.
    wrong = backward.clone()
    wrong[:, : shape[1] // 2] *= 1.1
    _, _, _, checked = left_right_check(forward, wrong, c2w, k, 1.0)
    left = landed & (source_uv[..., 0] < shape[1] // 2)
    assert not checked[left].any() and torch.equal(checked[~left], landed[~left])
    # Source pixels their own sweep dropped drop the reference pixels that land on them.
    keep = torch.ones(shape, dtype=torch.bool)
    keep[: shape[0] // 2] = False
    _, _, _, kept = left_right_check(forward, backward, c2w, k, 1.0, keep)
    assert torch.equal(kept, landed & (source_uv[..., 1] >= shape[0] // 2))


def test_the_banded_sweep_equals_one_band():
    images, c2w, k = plane_pair()
    reference, source = grey(images[0])[:60], grey(images[1])[:60]
    k = k.float()
    options = StereoOptions()
    inverse = plane_inverse_depths(c2w.float(), k, *reference.shape, NEAR, FAR, options)
    whole = plane_sweep_depth(reference, source, c2w.float(), k, inverse, options, max_band_entries=1 << 30)
    banded = plane_sweep_depth(reference, source, c2w.float(), k, inverse, options,
                               max_band_entries=inverse.shape[0] * reference.shape[1] * 7)  # bands of 7 rows
    assert torch.equal(whole.keep, banded.keep)
    assert torch.allclose(whole.depth, banded.depth, rtol=1e-6)
    assert int(whole.keep.sum()) > 1000


def test_planes_step_by_at_most_the_asked_shift_in_the_source_view():
    images, c2w, k = plane_pair()
    k = k.float()
    for step in (1.0, 0.5):
        options = StereoOptions(plane_step_pixels=step)
        inverse = plane_inverse_depths(c2w.float(), k, *images[0].shape, NEAR, FAR, options)
        rays = torch.tensor([[0.0, 0.0, -1.0]]) @ c2w[0, :3, :3].float().T  # the centre pixel's ray at z 1
        points = c2w[0, :3, 3].float() + rays / inverse[:, None]
        proj = project_to_camera(points, c2w[1].float().expand(len(inverse), 3, 4), k[1].expand(len(inverse), 4))
        shifts = (proj.pixels[1:] - proj.pixels[:-1]).norm(dim=-1)
        assert float(shifts.max()) <= step + 1e-3 and float(shifts.max()) >= 0.5 * step


def test_best_plane_refines_a_parabola_to_its_peak_and_drops_ends_and_twin_peaks():
    inverse = torch.linspace(1.0, 0.1, 10, dtype=torch.float64)
    index = torch.arange(10, dtype=torch.float64)
    options = StereoOptions(min_ncc=0.5, min_std=0.0, uniqueness_pixels=2.0, plane_step_pixels=1.0)
    peak = 1.0 - 0.05 * (index - 4.3) ** 2
    at_end = 1.0 - 0.05 * (index - 9.0) ** 2
    twins = torch.where((index == 2) | (index == 7), 0.95, 0.2)
    scores = torch.stack([peak, at_end, twins], 1)
    found = best_plane(scores, inverse, torch.ones(3), options)
    step = float(inverse[1] - inverse[0])
    assert abs(1.0 / float(found.depth[0]) - (1.0 + 4.3 * step)) < 1e-9
    assert found.keep.tolist() == [True, False, False]
    # A window without texture fails however well it scores.
    assert not best_plane(scores[:, :1], inverse, torch.zeros(1), dataclasses.replace(options, min_std=0.01)).keep.item()


def test_stereo_points_add_to_sifts_with_their_own_observations():
    images, c2w, k = plane_pair()
    sift = triangulate_training_views(images, c2w, k, TriangulationOptions(), (NEAR, FAR), progress=False)
    both = triangulate_training_views(images, c2w, k, TriangulationOptions(dense_stereo=True), (NEAR, FAR), progress=False)
    stereo = both.num_points - sift.num_points
    assert stereo > 5 * sift.num_points
    assert torch.equal(both.points[: sift.num_points], sift.points)
    # Each stereo point has one observation per view, at its distance from that camera, on its pixel's ray.
    extra = both.point >= sift.num_points
    assert torch.bincount(both.point[extra] - sift.num_points).eq(2).all()
    assert torch.equal(torch.bincount(both.view[extra]), torch.tensor([stereo] * 2))
    obs_points = both.points[both.point]
    assert torch.allclose((obs_points - c2w[both.view, :3, 3]).norm(dim=-1), both.depth, rtol=1e-9)
    proj = project_to_camera(obs_points, c2w[both.view], k[both.view])
    assert torch.allclose(proj.pixels[extra], both.pixels[extra], atol=2e-3)


def test_without_bounds_the_stereo_depth_range_comes_from_sifts_points():
    images, c2w, k = plane_pair()
    sift = triangulate_training_views(images, c2w, k, TriangulationOptions(), None, progress=False)
    near, far = z_depth_range(sift, c2w, k)
    z = project_to_camera(sift.points[sift.point], c2w[sift.view], k[sift.view]).depth
    assert near < float(z.min()) and far > float(z.max())
    both = triangulate_training_views(images, c2w, k, TriangulationOptions(dense_stereo=True), None, progress=False)
    assert both.num_points > 5 * sift.num_points
    empty = concatenate([])
    assert empty.num_points == 0 and z_depth_range(empty, c2w, k) is None
    assert isinstance(empty, SparseDepth)


def test_the_stereo_option_keys_the_cache_only_when_on():
    images = [np.zeros((4, 5, 3), np.uint8), np.ones((4, 5, 3), np.uint8)]
    c2w, k = torch.eye(4)[:3].expand(2, 3, 4), intrinsics(2)
    assert "dense_stereo" not in TriangulationOptions().key()
    assert cache_key(images, c2w, k, TriangulationOptions(dense_stereo=True)) != cache_key(images, c2w, k, TriangulationOptions())
