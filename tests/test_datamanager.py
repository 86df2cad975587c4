"""FrugalDataManager: patch-sampled training rays, spiral novel rays, nearest views, determinism."""

import pytest
import torch

from tests.helpers import manager_for


@pytest.fixture(scope="module")
def manager(procedural_scene):
    return manager_for(procedural_scene)


def test_training_rays_come_in_k_by_k_patches(manager):
    bundle, batch = manager.next_train(0)
    k = 3
    num_train = batch.num_train
    assert num_train == (100 // 9) * 9 == manager.get_train_rays_per_batch()
    assert batch.patch_size == k
    patches = batch.indices.reshape(-1, k * k, 3)
    for patch in patches:
        view, top, left = patch[0].tolist()
        rows, cols = torch.meshgrid(torch.arange(k) + top, torch.arange(k) + left, indexing="ij")
        assert (patch[:, 0] == view).all()
        assert patch[:, 1].tolist() == rows.flatten().tolist()
        assert patch[:, 2].tolist() == cols.flatten().tolist()
    idx = batch.indices
    assert torch.equal(batch.image, manager.train_images[idx[:, 0], idx[:, 1], idx[:, 2]])
    # Each training ray is the one nerfstudio generates for its pixel.
    cameras = manager.train_dataset.cameras
    for ray in (0, 7, num_train - 1):
        view, row, col = idx[ray].tolist()
        expected = cameras.generate_rays(camera_indices=view)
        assert torch.allclose(bundle.origins[ray], expected.origins[row, col], atol=1e-5)
        assert torch.allclose(bundle.directions[ray], expected.directions[row, col], atol=1e-5)


def test_novel_rays_follow_the_training_rays_and_come_from_the_spiral(manager):
    bundle, batch = manager.next_train(1)
    num_train = batch.num_train
    novel = batch.novel_indices
    assert novel.shape == (40, 3) and bundle.origins.shape[0] == num_train + 40
    # 2x2 patches: consecutive groups of four share a pose and cover a 2x2 block.
    groups = novel.reshape(-1, 4, 3)
    assert (groups[:, :, 0] == groups[:, :1, 0]).all()
    assert (groups[:, :, 1] - groups[:, :1, 1]).tolist() == [[0, 0, 1, 1]] * len(groups)
    assert (groups[:, :, 2] - groups[:, :1, 2]).tolist() == [[0, 1, 0, 1]] * len(groups)
    spiral = manager.novel_cameras
    assert spiral is not None and len(spiral) == manager.config.num_novel_poses
    centers = spiral.camera_to_worlds[novel[:, 0], :3, 3]
    assert torch.allclose(bundle.origins[num_train:], centers, atol=1e-5)
    train_centers = manager.train_dataset.cameras.camera_to_worlds[:, :3, 3]
    expected = torch.cdist(centers, train_centers).argmin(dim=-1)
    assert torch.equal(batch.nearest_view[num_train:], expected)


def test_training_views_warp_into_their_nearest_other_view(manager):
    _, batch = manager.next_train(2)
    centers = manager.train_dataset.cameras.camera_to_worlds[:, :3, 3]
    distance = torch.cdist(centers, centers) + torch.diag(torch.full((len(centers),), float("inf")))
    expected = distance.argmin(dim=-1)
    assert torch.equal(manager.train_nearest_view, expected)
    view = batch.indices[:, 0]
    assert torch.equal(batch.nearest_view[batch.train], expected[view])
    assert (batch.nearest_view[batch.train] != view).all()
    # The views warps compare with are held once by the datamanager (the pipeline hands them to the model).
    num_views = len(centers)
    assert manager.warp_images.shape == (num_views, *manager.train_images.shape[1:3], 3)
    assert manager.warp_camera_to_worlds.shape == (num_views, 3, 4) and manager.warp_intrinsics.shape == (num_views, 4)
    assert not any(isinstance(v, torch.Tensor) and v.shape[0] == num_views and v.ndim == 4 for v in vars(batch).values())


def test_batches_are_deterministic_under_the_seed(procedural_scene):
    first, second = manager_for(procedural_scene), manager_for(procedural_scene)
    other = manager_for(procedural_scene, seed=1)
    for step in range(3):
        a, b, c = first.next_train(step)[1], second.next_train(step)[1], other.next_train(step)[1]
        assert torch.equal(a.indices, b.indices) and torch.equal(a.novel_indices, b.novel_indices)
    assert not torch.equal(a.indices, c.indices)


def test_novel_views_can_be_turned_off(procedural_scene):
    manager = manager_for(procedural_scene, novel_views=False)
    bundle, batch = manager.next_train(0)
    assert batch.novel_indices is None and batch.num_novel == 0 and bundle.origins.shape[0] == batch.num_train


@pytest.fixture
def keep_points_outside_the_box(monkeypatch):
    """The procedural scene's few SIFT points lie on its backdrop, outside the scene box, which the
    datamanager drops (tested in test_sparse_points); keep them here to test the rays."""
    monkeypatch.setattr("frugalnerf_ns.data.training_points.points_inside_box", lambda sparse, aabb: sparse)


def test_sparse_rays_follow_the_novel_rays_and_pass_through_their_points(procedural_scene, tmp_path, keep_points_outside_the_box):
    manager = manager_for(procedural_scene, min_sparse_points=1, num_sparse_rays_per_batch=3, sparse_cache_dir=tmp_path)
    sparse = manager.sparse
    assert sparse is not None and sparse.num_points >= 1
    bundle, batch = manager.next_train(0)
    num_train, num_novel = batch.num_train, batch.num_novel
    depth = batch.sparse_depth
    assert num_novel == 40 and depth.shape == (min(3, len(sparse.view)),)
    start = num_train + num_novel
    assert bundle.origins.shape[0] == start + depth.shape[0]
    # Each sparse ray, walked out to its target depth, lands on one of the triangulated points.
    ends = bundle.origins[start:] + bundle.directions[start:] * depth[:, None]
    assert torch.cdist(ends, sparse.points.float()).amin(dim=1).max() < 1e-4
    assert len(list(tmp_path.glob("sparse_depth_*.npz"))) == 1


def test_sparse_cache_is_reused_and_a_corrupt_one_rebuilt(procedural_scene, tmp_path, capsys, keep_points_outside_the_box):
    first = manager_for(procedural_scene, min_sparse_points=1, sparse_cache_dir=tmp_path)
    (path,) = tmp_path.glob("sparse_depth_*.npz")
    stamp = path.stat().st_mtime_ns
    again = manager_for(procedural_scene, min_sparse_points=1, sparse_cache_dir=tmp_path)
    assert path.stat().st_mtime_ns == stamp and torch.equal(again.sparse.points, first.sparse.points)
    capsys.readouterr()
    path.write_bytes(b"\x00garbage")
    rebuilt = manager_for(procedural_scene, min_sparse_points=1, sparse_cache_dir=tmp_path)
    assert "corrupt" in capsys.readouterr().out
    assert torch.equal(rebuilt.sparse.points, first.sparse.points) and path.stat().st_size > 100


def test_too_few_sparse_points_train_without_sparse_depth_and_say_so(procedural_scene, tmp_path, capsys):
    manager = manager_for(procedural_scene, min_sparse_points=10_000, sparse_cache_dir=tmp_path)
    out = capsys.readouterr().out
    assert manager.sparse is None and "without the sparse depth loss" in out
    _, batch = manager.next_train(0)
    assert batch.sparse_depth is None and batch.sparse.start == batch.sparse.stop  # no sparse-depth rays


def test_one_rgba_image_among_rgb_images(procedural_scene, tmp_path):
    """Every image of a dataset gets the same channels: RGBA when any has alpha (opaque for the others)."""
    import shutil

    import numpy as np
    from PIL import Image

    scene = tmp_path / "mixed"
    shutil.copytree(procedural_scene, scene)
    for name in ("frame_000.png", "frame_002.png"):  # a training view and a test view
        rgb = np.asarray(Image.open(scene / "images" / name).convert("RGB"))
        alpha = np.full(rgb.shape[:2] + (1,), 255, dtype=np.uint8)
        alpha[:10, :10] = 0
        Image.fromarray(np.concatenate([rgb, alpha], axis=-1), "RGBA").save(scene / "images" / name)
    manager = manager_for(scene)
    images = manager.train_images
    assert images.shape[-1] == 4
    assert (images[0, :10, :10, 3] == 0).all() and (images[0, 10:, 10:, 3] == 1).all()
    assert (images[1:, ..., 3] == 1).all()  # the RGB files: opaque
    # Warps compare colours composited on white.
    assert torch.allclose(manager.warp_images[0, :10, :10], torch.ones(10, 10, 3))
    bundle, batch = manager.next_train(0)
    assert batch.image.shape[-1] == 4
    # The eval batch collates every test image (one RGBA, one RGB) without a stacking error.
    _, eval_batch = manager.next_eval(0)
    assert eval_batch.image.shape[-1] == 4
