"""Sparse depth: pycolmap SIFT + matching, torch triangulation with fixed cameras, cache, L_sd."""

import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.cache import cache_file_name
from frugalnerf_ns.model.losses import inverse_depth_loss, relative_disparity_loss
from frugalnerf_ns.progress import Progress
from frugalnerf_ns.geometry.reprojection import project_to_camera
from tests.photo_scene import texture
from tests.plane_scene import FOCAL, HEIGHT, PLANE_Z, WIDTH, camera, intrinsics, render_plane
from frugalnerf_ns.data.sparse_points import (
    SparseDepth,
    TriangulationOptions,
    build_tracks,
    extract_sift,
    match_descriptors,
    match_pairs,
    neighbour_pairs,
    opencv_projection_matrices,
    triangulate_dlt,
    triangulate_tracks,
    triangulate_training_views,
)
from frugalnerf_ns.data.training_points import cache_key, load_sparse_depth, save_sparse_depth

FERN = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "llff" / "fern"

def test_opencv_projection_matrices_agree_with_project_to_camera():
    c2w = torch.stack([camera((0.3, 0.2, 2.0)), camera((-0.4, 0.1, 2.5), (0.1, 0.0, 0.0))])
    k = torch.tensor([[300.0, 310.0, 150.0, 120.0], [280.0, 290.0, 160.0, 110.0]], dtype=torch.float64)
    points = torch.randn(20, 3, dtype=torch.float64) * 0.3
    p = opencv_projection_matrices(c2w, k)
    for view in range(2):
        hom = torch.cat([points, torch.ones(20, 1, dtype=torch.float64)], -1) @ p[view].T
        expected = project_to_camera(points, c2w[view].expand(20, 3, 4), k[view].expand(20, 4))
        assert torch.allclose(hom[:, :2] / hom[:, 2:], expected.pixels, atol=1e-9)
        assert torch.allclose(hom[:, 2], expected.depth, atol=1e-9)


def test_dlt_recovers_points_exactly_and_matches_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    c2w = torch.stack([camera((0.3, 0.2, 2.0)), camera((-0.4, 0.1, 2.5)), camera((0.0, -0.5, 2.2))])
    k = intrinsics(3)
    points = torch.randn(50, 3, dtype=torch.float64) * 0.3
    view = torch.tensor([[0, 1, 2]]).expand(50, 3)
    pixels = project_to_camera(points[:, None].expand(-1, 3, -1), c2w[view], k[view]).pixels
    assert torch.allclose(triangulate_dlt(opencv_projection_matrices(c2w, k), view, pixels), points, atol=1e-7)
    # Two views, against pycolmap's own triangulation (normalised image coordinates, OpenCV cameras).
    p = opencv_projection_matrices(c2w, k)
    kinv = torch.linalg.inv(p.new_tensor([[FOCAL, 0, WIDTH / 2], [0, FOCAL, HEIGHT / 2], [0, 0, 1]]))
    cam_from_world = [(kinv @ p[i]).numpy() for i in (0, 1)]
    normalised = [((kinv[:2, :2] @ pixels[0, i, :, None]) + kinv[:2, 2:]).numpy() for i in (0, 1)]
    theirs = pycolmap.triangulate_point(cam_from_world[0], cam_from_world[1], normalised[0], normalised[1])
    ours = triangulate_dlt(p, view[:1, :2], pixels[:1, :2])[0]
    assert np.allclose(np.asarray(theirs).ravel(), ours.numpy(), atol=1e-6)


def test_tracks_join_pairwise_matches_and_drop_contradictions():
    matches = {
        (0, 1): np.array([[0, 0], [2, 2]]),
        (1, 2): np.array([[0, 5], [2, 3]]),
        (0, 2): np.array([[0, 5], [2, 4]]),  # feature 2 of view 0 reaches features 3 and 4 of view 2
    }
    tracks = build_tracks(matches, [3, 3, 6])
    assert tracks == [[(0, 0), (1, 0), (2, 5)]]


def test_filters_drop_bad_points():
    c2w = torch.stack([camera((0.2, 0.0, 2.0)), camera((-0.2, 0.0, 2.0))])
    k = intrinsics(2)
    good, behind, far_off = [0.0, 0.0, 0.0], [0.0, 0.0, 3.0], [0.1, 0.1, -0.5]
    points = torch.tensor([good, behind, far_off], dtype=torch.float64)
    # Exact projective images (a point behind the camera too), so DLT recovers each point as it is.
    hom = torch.einsum("vij,pj->pvi", opencv_projection_matrices(c2w, k), torch.cat([points, torch.ones(3, 1, dtype=torch.float64)], -1))
    pixels = hom[..., :2] / hom[..., 2:]
    pixels[2, 1] += torch.tensor([0.0, 6.0], dtype=torch.float64)  # a wrong match off the epipolar line
    keypoints = [pixels[:, 0], pixels[:, 1]]
    tracks = [[(0, i), (1, i)] for i in range(3)]
    options = TriangulationOptions(max_reprojection_error=1.0, min_triangulation_angle=0.5)
    sparse = triangulate_tracks(tracks, keypoints, c2w, k, options)
    # The point behind both cameras and the one that reprojects 3 px off are gone.
    assert sparse.num_points == 1 and torch.allclose(sparse.points[0], points[0], atol=1e-6)
    assert torch.allclose(sparse.depth, (points[0] - c2w[:, :3, 3]).norm(dim=-1), atol=1e-6)
    # Depth bounds (near, far along the optical axis) and the triangulation angle also filter.
    assert triangulate_tracks(tracks, keypoints, c2w, k, options, depth_bounds=(2.5, 10.0)).num_points == 0
    wide = TriangulationOptions(max_reprojection_error=1.0, min_triangulation_angle=30.0)  # the pair sees it at ~11.4 deg
    assert triangulate_tracks(tracks, keypoints, c2w, k, wide).num_points == 0


def test_sift_triangulation_on_a_textured_plane_recovers_its_depth():
    tex = texture()
    c2w = torch.stack([camera((0.25, 0.1, 2.0)), camera((-0.25, -0.05, 2.1))])
    images = [render_plane(c, tex) for c in c2w]
    sparse = triangulate_training_views(images, c2w, intrinsics(2), TriangulationOptions(max_reprojection_error=1.0))
    assert sparse.num_points >= 500
    true_z = PLANE_Z - 0.2 * sparse.points[:, 0]
    # Relative depth error of each point along the first camera's axis: median below 0.5 %, 95 % below 2 %.
    depth = project_to_camera(sparse.points, c2w[0].expand(sparse.num_points, 3, 4), intrinsics(sparse.num_points)).depth
    rel = (sparse.points[:, 2] - true_z).abs() / depth
    assert float(rel.median()) < 0.005 and float(rel.quantile(0.95)) < 0.02
    # Every observation's pixel ray passes through its point at the stored distance.
    proj = project_to_camera(sparse.points[sparse.point], c2w[sparse.view], intrinsics(len(sparse.view)))
    assert torch.allclose(proj.pixels, sparse.pixels, atol=1e-6)


def test_inverse_depth_loss_value_gradient_and_empty():
    rendered = torch.tensor([2.0, 4.0, 0.0], requires_grad=True)
    target = torch.tensor([2.0, 2.0, 1.0])
    loss = inverse_depth_loss(rendered, target)
    expected = ((0.0) ** 2 + (0.25 - 0.5) ** 2 + (1 / 1e-3 - 1.0) ** 2) / 3
    assert float(loss.detach()) == pytest.approx(expected, rel=1e-5)
    loss.backward()
    assert torch.isfinite(rendered.grad).all()
    # Too far (4 > 2): gradient descent brings the rendered depth closer.
    assert rendered.grad[1] > 0 and rendered.grad[0] == 0
    assert float(inverse_depth_loss(torch.zeros(0), torch.zeros(0))) == 0.0


def test_relative_disparity_loss_is_scale_free_huber_and_bounded():
    rendered = torch.tensor([2.0, 1.0, 20.0, 0.0], requires_grad=True)
    target = torch.tensor([2.0, 1.1, 25.0, 30.0])
    loss = relative_disparity_loss(rendered, target, delta=0.2)
    errors = [0.0, 0.1, 0.25, 30.0 / 1e-3 - 1.0]  # target / rendered - 1, the empty ray clamped at 1e-3
    per_point = [0.5 * e * e / 0.2 if e < 0.2 else e - 0.1 for e in errors]
    assert float(loss.detach()) == pytest.approx(sum(per_point) / 4, rel=1e-5)
    loss.backward()
    assert torch.isfinite(rendered.grad).all() and rendered.grad[0] == 0
    # Too near (20 < 25, 1 < 1.1): gradient descent moves the rendered depth out.
    assert rendered.grad[1] < 0 and rendered.grad[2] < 0
    # The same relative error weighs the same at any distance (Eq. 11's inverse MSE: 100x less at 10x the depth).
    near = relative_disparity_loss(torch.tensor([1.0]), torch.tensor([1.5]))
    far = relative_disparity_loss(torch.tensor([10.0]), torch.tensor([15.0]))
    assert float(near) == pytest.approx(float(far), rel=1e-6)
    assert float(inverse_depth_loss(torch.tensor([1.0]), torch.tensor([1.5]))) == pytest.approx(
        100 * float(inverse_depth_loss(torch.tensor([10.0]), torch.tensor([15.0]))), rel=1e-5)
    assert float(relative_disparity_loss(torch.zeros(0), torch.zeros(0))) == 0.0


def _sparse(n=4):
    return SparseDepth(torch.rand(n, 3).double(), torch.zeros(n).long(), torch.arange(n), torch.rand(n, 2).double(), torch.rand(n).double() + 1)


def test_cache_round_trip_stale_and_corrupt(tmp_path):
    path = tmp_path / cache_file_name(["images/image006.png", "images/image013.png"], 504, 378, "sparse_depth")
    assert path.name == "sparse_depth_image006-image013_504x378.npz"
    assert load_sparse_depth(path, "k")[1] == "missing"
    sparse = _sparse()
    save_sparse_depth(path, sparse, "k")
    loaded, why = load_sparse_depth(path, "k")
    assert why == "" and all(torch.equal(a, b) for a, b in zip(loaded, sparse))
    assert load_sparse_depth(path, "other")[0] is None and "stale" in load_sparse_depth(path, "other")[1]
    path.write_bytes(b"not a numpy archive")
    assert load_sparse_depth(path, "k")[0] is None and "corrupt" in load_sparse_depth(path, "k")[1]
    broken = _sparse()._replace(point=torch.tensor([0, 1, 2, 9]))  # a point index past the points
    save_sparse_depth(path, broken, "k")
    assert "corrupt" in load_sparse_depth(path, "k")[1]


def test_cache_key_follows_images_cameras_options_and_bounds():
    images = [np.zeros((4, 5, 3), np.uint8), np.ones((4, 5, 3), np.uint8)]
    c2w, k, opts = torch.eye(4)[:3].expand(2, 3, 4), intrinsics(2), TriangulationOptions()
    base = cache_key(images, c2w, k, opts)
    assert base == cache_key([i.copy() for i in images], c2w.clone(), k.clone(), TriangulationOptions())
    changed = [images[0], images[1].copy()]
    changed[1][0, 0, 0] = 9
    assert cache_key(changed, c2w, k, opts) != base
    assert cache_key(images, c2w + 0.01, k, opts) != base
    assert cache_key(images, c2w, k, TriangulationOptions(max_reprojection_error=3.0)) != base
    assert cache_key(images, c2w, k, opts, (1.0, 5.0)) != base
    assert cache_key(images, c2w, k, TriangulationOptions(sift_upsample=2)) != base
    # The default SIFT size adds nothing to the key: caches written before the option still match.
    assert set(opts.key()) == {"max_reprojection_error", "min_track_length", "min_triangulation_angle", "max_features", "match_neighbors"}


def fern_two_views():
    """The gate's fern pair at 1/8 size as the parser gives it: images, cameras, intrinsics, near/far bounds."""
    from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig

    outputs = LLFFDataParserConfig(data=FERN, downscale_factor=8, train_views=(6, 13)).setup().get_dataparser_outputs("train")
    cams = outputs.cameras
    images = [np.asarray(Image.open(f).convert("RGB")) for f in outputs.image_filenames]
    k = torch.stack([cams.fx[:, 0], cams.fy[:, 0], cams.cx[:, 0], cams.cy[:, 0]], -1).double()
    return images, cams, k, tuple(float(b) for b in outputs.metadata["near_far"])


@pytest.mark.skipif(not FERN.exists(), reason="../shared/data is absent")
def test_fern_two_views_give_plausible_points_inside_the_llff_bounds():
    images, cams, k, (near, far) = fern_two_views()
    sparse = triangulate_training_views(images, cams.camera_to_worlds.double(), k)
    assert 100 <= sparse.num_points <= 5000
    # Without the bounds as a filter, nearly all points already lie inside them (COLMAP's own bounds).
    depth = project_to_camera(sparse.points[sparse.point], cams.camera_to_worlds.double()[sparse.view], k[sparse.view]).depth
    inside = ((depth >= near) & (depth <= far)).double().mean()
    assert float(inside) >= 0.95


def test_points_outside_the_scene_box_are_dropped_with_their_observations():
    from frugalnerf_ns.data.sparse_points import points_inside_box

    points = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.5, -0.5, 0.9]], dtype=torch.float64)
    sparse = SparseDepth(
        points, torch.tensor([0, 1, 0, 1, 0, 1]), torch.tensor([0, 0, 1, 1, 2, 2]),
        torch.arange(12, dtype=torch.float64).reshape(6, 2), torch.arange(1, 7, dtype=torch.float64),
    )
    kept = points_inside_box(sparse, torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]))
    assert kept.num_points == 2 and torch.equal(kept.points, points[[0, 2]])
    assert kept.point.tolist() == [0, 0, 1, 1] and kept.depth.tolist() == [1, 2, 5, 6]
    assert torch.equal(kept.pixels, sparse.pixels[[0, 1, 4, 5]])


def test_the_sparse_points_line_counts_the_points_the_box_left_out():
    from frugalnerf_ns.data.training_points import usable_points

    points = torch.tensor([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.5, -0.5, 0.9]], dtype=torch.float64)
    sparse = SparseDepth(
        points, torch.tensor([0, 1, 0, 1, 0, 1]), torch.tensor([0, 0, 1, 1, 2, 2]),
        torch.arange(12, dtype=torch.float64).reshape(6, 2), torch.arange(1, 7, dtype=torch.float64),
    )
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    lines = []
    kept = usable_points(sparse, box, 2, lines.append, "triangulating")
    assert kept is not None and kept.num_points == 2
    assert lines == ["frugalnerf: 2 sparse points from triangulating supervise depth (L_sd) (1 more lie outside the scene box)."]
    lines.clear()
    assert usable_points(sparse, box, 3, lines.append, "triangulating") is None
    assert "found 2 points (1 more lie outside the scene box)" in lines[0] and "without the sparse depth loss" in lines[0]
    lines.clear()
    assert usable_points(sparse, None, 3, lines.append, "triangulating").num_points == 3  # NDC: no box, no count
    assert "outside" not in lines[0]


@pytest.mark.skipif(not FERN.exists(), reason="../shared/data is absent")
def test_torch_matching_agrees_with_pycolmaps_matcher_on_fern():
    """The same rule as COLMAP's SIFT matcher (ratio 0.8, 0.7 rad, cross-check): nearly the same matches."""
    import pycolmap

    files = sorted((FERN / "images_8").iterdir())
    images = [np.asarray(Image.open(files[i]).convert("RGB")) for i in (6, 13)]
    keypoints, descriptors = extract_sift(images, 8192, progress=False)
    ours = {tuple(m) for m in match_descriptors(descriptors[0], descriptors[1]).tolist()}
    extractor = pycolmap.FeatureExtractor.create(pycolmap.FeatureExtractionOptions(), pycolmap.Device.cpu)
    grey = [np.clip(im.astype(np.float32) @ [0.299, 0.587, 0.114], 0, 255).astype(np.uint8) for im in images]
    features = [extractor.extract_from_uint8_array(np.ascontiguousarray(g)) for g in grey]
    assert [len(f[0]) for f in features] == [len(k) for k in keypoints]  # the same features, in the same order
    matcher = pycolmap.FeatureMatcher.create(pycolmap.FeatureMatchingOptions(), pycolmap.Device.cpu)
    theirs = {tuple(m) for m in np.asarray(matcher.match(*features[0], *features[1])).reshape(-1, 2).tolist()}
    assert len(theirs) >= 200
    assert len(ours & theirs) >= 0.97 * len(theirs) and len(ours) <= 1.03 * len(theirs)


def test_a_blank_image_has_no_features_and_no_matches():
    tex = texture()
    images = [np.zeros((HEIGHT, WIDTH), np.uint8), render_plane(camera((0.1, 0.0, 2.0)), tex)]
    keypoints, descriptors = extract_sift(images, 8192, progress=False)
    assert keypoints[0].shape == (0, 2) and descriptors[0].shape == (0, 128) and len(keypoints[1]) > 100
    assert match_descriptors(descriptors[0], descriptors[1]).shape == (0, 2)


def test_matching_keeps_mutual_distinct_nearest_neighbours_only():
    gen = torch.Generator().manual_seed(0)
    a = torch.nn.functional.normalize(torch.rand(50, 128, generator=gen), dim=-1)
    b = torch.nn.functional.normalize(a[torch.arange(49, -1, -1)] + 0.01 * torch.rand(50, 128, generator=gen), dim=-1)
    matches = match_descriptors(a, b)
    assert sorted(matches.tolist()) == [[i, 49 - i] for i in range(50)]
    # A descriptor with two equally close candidates fails the ratio test.
    twin = torch.cat([b, b[:1]])  # b[0] is a[49]'s partner
    assert 49 not in match_descriptors(a, twin)[:, 0].tolist() and len(match_descriptors(a, twin)) == 49
    assert match_descriptors(a[:1], b).shape == (0, 2)


def ring_of_cameras(count):
    angles = torch.arange(count, dtype=torch.float64) * 2 * math.pi / count
    return torch.stack([camera((3 * math.cos(a), 0.3, 3 * math.sin(a))) for a in angles.tolist()])


def test_neighbour_pairs_grow_linearly_and_join_nearby_cameras():
    assert neighbour_pairs(ring_of_cameras(6), neighbors=8) == [(i, j) for i in range(6) for j in range(i + 1, 6)]
    for count in (30, 100):
        pairs = neighbour_pairs(ring_of_cameras(count), neighbors=8)
        # On a ring each camera's 8 nearest are the 4 on either side: exactly 4 pairs per view.
        assert len(pairs) == 4 * count < count * (count - 1) // 2
        gaps = {min((j - i) % count, (i - j) % count) for i, j in pairs}
        assert gaps == {1, 2, 3, 4}
        assert all(i < j for i, j in pairs)


def test_feature_cap_keeps_the_largest_scale_features():
    tex = texture()
    image = render_plane(camera((0.1, 0.0, 2.0)), tex)
    full, _ = extract_sift([image], 8192, progress=False)
    capped, descriptors = extract_sift([image], 100, progress=False)
    assert len(full[0]) > 300 and len(capped[0]) == 100 and descriptors[0].shape == (100, 128)
    assert torch.allclose(descriptors[0].norm(dim=-1), torch.ones(100))
    kept = {tuple(p) for p in capped[0].tolist()}
    assert kept <= {tuple(p) for p in full[0].tolist()}


def test_match_pairs_prints_progress_only_when_it_takes_long(monkeypatch, capsys):
    import frugalnerf_ns.data.sparse_points as sparse_points

    descriptors = [torch.nn.functional.normalize(torch.rand(20, 128), dim=-1) for _ in range(4)]
    pairs = neighbour_pairs(ring_of_cameras(4), neighbors=3)
    match_pairs(descriptors, pairs)
    assert capsys.readouterr().out == ""  # a fast start-up stays silent
    now = [0.0]

    def slow_clock():
        now[0] += 2.0  # every pair "takes" 2 s
        return now[0]

    monkeypatch.setattr(sparse_points, "Progress", lambda *a, **k: Progress(*a, **{**k, "clock": slow_clock}))
    matches = match_pairs(descriptors, pairs)
    lines = capsys.readouterr().out.splitlines()
    assert len(matches) == len(pairs) == 6
    assert lines and lines[-1].startswith("frugalnerf sparse points: matching: pair 6/6")


def test_sift_on_an_enlarged_image_places_points_as_accurately_and_in_the_images_pixels():
    tex = texture()
    c2w = torch.stack([camera((0.25, 0.1, 2.0)), camera((-0.25, -0.05, 2.1))])
    images = [render_plane(c, tex) for c in c2w]
    enlarged = triangulate_training_views(
        images, c2w, intrinsics(2), TriangulationOptions(max_reprojection_error=1.0, sift_upsample=2), progress=False
    )
    assert enlarged.num_points >= 500
    true_z = PLANE_Z - 0.2 * enlarged.points[:, 0]
    depth = project_to_camera(enlarged.points, c2w[0].expand(enlarged.num_points, 3, 4), intrinsics(enlarged.num_points)).depth
    rel = (enlarged.points[:, 2] - true_z).abs() / depth
    assert float(rel.median()) < 0.005 and float(rel.quantile(0.95)) < 0.02
    # The same features found at both sizes sit at the same place in the image's pixels: no half-pixel shift
    # from mapping the enlarged image's coordinates back.
    small, _ = extract_sift(images[:1], 8192, progress=False)
    large, _ = extract_sift(images[:1], 8192, progress=False, upsample=2)
    distance, nearest = torch.cdist(small[0], large[0]).min(dim=1)
    paired = distance < 0.75
    assert int(paired.sum()) >= 100
    offset = (large[0][nearest[paired]] - small[0][paired]).mean(dim=0)
    assert float(offset.abs().max()) < 0.1


@pytest.mark.skipif(not FERN.exists(), reason="../shared/data is absent")
def test_fern_at_1_8_gives_several_times_the_points_with_sift_on_enlarged_images():
    images, cams, k, bounds = fern_two_views()
    counts = [triangulate_training_views(images, cams.camera_to_worlds.double(), k, TriangulationOptions(sift_upsample=up),
                                         bounds, progress=False).num_points for up in (1, 2)]
    # 412 and 1471 when written: the finest texture of a 504x378 image is below SIFT's smallest scale.
    assert counts[1] >= 2.5 * counts[0]


def test_a_sift_upsample_below_one_is_refused():
    with pytest.raises(ValueError, match="upsample"):
        extract_sift([np.zeros((32, 32), np.uint8)], 100, progress=False, upsample=0)
