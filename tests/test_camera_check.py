"""The camera check: right cameras explain the training photos' matches, broken copies of them (focal x0.8 and
x1.25, principal point moved by 10 % of the width, OpenCV axes read as OpenGL, images turned by 90 degrees, poses of
another scene) do not, and the check names the cause it can. On the procedural scene with exact correspondences, and
on fern's paper split through SIFT (skipped where ../shared/data is absent); the start-up summary of a broken fern
copy warns once."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.camera_check import CameraCheck, check_cameras, check_matches
from frugalnerf_ns.data.procedural_scene import SceneSpec, blender_camera_poses, camera_poses
from frugalnerf_ns.data.sparse_points import TriangulationOptions
from frugalnerf_ns.data.training_points import all_training_sparse_depth
from frugalnerf_ns.geometry.reprojection import project_to_camera

FERN = Path(__file__).resolve().parents[2] / "shared" / "data" / "llff" / "fern"
needs_fern = pytest.mark.skipif(not FERN.is_dir(), reason=f"real LLFF scene not present at {FERN}")
SPEC = SceneSpec(width=320, height=240, focal=300.0)


def broken(c2w: torch.Tensor, K: torch.Tensor, width: int, other: torch.Tensor):
    """The broken copies of one set of cameras (what each changes), the images kept."""
    focal_low, focal_high, shifted, flipped = K.clone(), K.clone(), K.clone(), c2w.clone()
    focal_low[:, :2] *= 0.8
    focal_high[:, :2] *= 1.25
    shifted[:, 2] += 0.1 * width
    flipped[:, :3, 1:3] *= -1
    return {"focal x0.8": (c2w, focal_low), "focal x1.25": (c2w, focal_high), "principal point": (c2w, shifted),
            "axes": (flipped, K), "another scene": (other[: len(c2w)], K)}


def exact_matches(c2w: torch.Tensor, K: torch.Tensor, size, count: int = 300, noise: float = 0.2, seed: int = 0):
    """Keypoints where random points near the procedural scene's centre project (with ``noise`` pixels of
    jitter), matched between every pair of views: the correspondences SIFT would find on a well-textured scene."""
    gen = torch.Generator().manual_seed(seed)
    points = (torch.rand(count, 3, generator=gen, dtype=torch.float64) - 0.5) * 1.6 + torch.tensor([0.0, 0.0, 0.25])
    proj = project_to_camera(points[None].expand(len(c2w), -1, -1), c2w[:, None].expand(-1, count, -1, -1),
                             K[:, None].expand(-1, count, -1))
    inside = proj.in_front & (proj.pixels >= 0).all(-1) & (proj.pixels[..., 0] < size[0]) & (proj.pixels[..., 1] < size[1])
    keep = inside.all(dim=0)
    pixels = proj.pixels[:, keep] + noise * torch.randn(proj.pixels[:, keep].shape, generator=gen, dtype=torch.float64)
    ids = np.arange(int(keep.sum()))
    matches = {(i, j): np.stack([ids, ids], 1) for i in range(len(c2w)) for j in range(i + 1, len(c2w))}
    return list(pixels), matches


def procedural_cameras():
    poses = camera_poses(SPEC)
    c2w = torch.stack([poses[i][:3, :4] for i in SPEC.train_ids]).double()
    K = torch.tensor([[SPEC.focal, SPEC.focal, SPEC.width / 2, SPEC.height / 2]] * len(c2w), dtype=torch.float64)
    return c2w, K


def test_exact_correspondences_of_the_procedural_scene_flag_every_broken_copy_and_name_its_cause():
    c2w, K = procedural_cameras()
    size = (SPEC.width, SPEC.height)
    keypoints, matches = exact_matches(c2w, K, size)
    right = check_matches(keypoints, matches, c2w, K, size)
    assert right.judged and not right.flagged and right.median_error < 0.5
    assert right.focal_scale == pytest.approx(1.0) and right.centre_shift == pytest.approx((0.0, 0.0))
    other = torch.stack(blender_camera_poses(3, 4.0, seed=7))[:, :3, :4].double()
    checks = {name: check_matches(keypoints, matches, cams, k, size) for name, (cams, k) in broken(c2w, K, SPEC.width, other).items()}
    assert all(check.flagged for check in checks.values()), {n: c.facts() for n, c in checks.items()}
    assert "the focal length" in checks["focal x0.8"].causes[0] and checks["focal x0.8"].focal_scale == pytest.approx(1.25, abs=0.04)
    assert "the focal length" in checks["focal x1.25"].causes[0] and checks["focal x1.25"].focal_scale == pytest.approx(0.8, abs=0.03)
    principal = checks["principal point"]
    assert any("principal point" in c for c in principal.causes) and principal.centre_shift[0] == pytest.approx(-0.1)
    assert "behind a camera" in checks["axes"].causes[0]
    # Images turned by 90 degrees after the cameras were made: each keypoint where the turned image shows it.
    turned = [torch.stack([k[:, 1], SPEC.width - k[:, 0]], -1) for k in keypoints]
    assert check_matches(turned, matches, c2w, K, (SPEC.height, SPEC.width)).flagged


def test_too_few_matches_give_no_verdict():
    c2w, K = procedural_cameras()
    keypoints, matches = exact_matches(c2w, K, (SPEC.width, SPEC.height), count=6)
    check = check_matches(keypoints, matches, c2w, K * torch.tensor([0.8, 0.8, 1.0, 1.0], dtype=torch.float64),
                          (SPEC.width, SPEC.height))
    assert not check.judged and not check.flagged and check.causes == []


def test_a_repeated_texture_s_wrong_matches_are_dropped_before_the_cameras_are_judged():
    c2w, K = procedural_cameras()
    size = (SPEC.width, SPEC.height)
    keypoints, matches = exact_matches(c2w, K, size)
    gen = torch.Generator().manual_seed(3)
    count = len(keypoints[0])
    # A third more matches, each joining unrelated features (a checkerboard's period): one epipolar geometry per
    # pair explains the right ones only.
    noisy = [torch.cat([k, torch.rand(count // 3, 2, generator=gen, dtype=torch.float64) * torch.tensor(size)]) for k in keypoints]
    extra = np.arange(count, count + count // 3)
    wrong = {pair: np.concatenate([m, np.stack([extra, np.roll(extra, 5)], 1)]) for pair, m in matches.items()}
    check = check_matches(noisy, wrong, c2w, K, size)
    assert not check.flagged and check.median_error < 0.5 and check.matches <= count + 5


def fern_split():
    from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig

    outputs = LLFFDataParserConfig(data=FERN).setup().get_dataparser_outputs("train")
    cams = outputs.cameras
    images = [np.asarray(Image.open(p).convert("RGB")) for p in outputs.image_filenames]
    return images, cams.camera_to_worlds.double(), torch.cat([cams.fx, cams.fy, cams.cx, cams.cy], 1).double()


@needs_fern
def test_fern_as_published_is_not_flagged_and_each_broken_copy_is():
    images, c2w, K = fern_split()
    right = check_cameras(images, c2w, K)
    assert right.judged and not right.flagged and right.median_error < 0.5
    other = torch.stack(blender_camera_poses(2, 4.0, seed=7))[:, :3, :4].double()
    for name, (cams, k) in broken(c2w, K, images[0].shape[1], other).items():
        check = check_cameras(images, cams, k)
        assert check.flagged, (name, check.facts())
    turned = [np.ascontiguousarray(np.rot90(image)) for image in images]
    assert check_cameras(turned, c2w, K).flagged
    # A textured photo of another scene in place of one of fern's: hardly a match, flagged (not "no verdict").
    flower = np.asarray(Image.open(FERN.parent / "flower" / "images_8" / "image011.png").convert("RGB"))
    unrelated = check_cameras([images[0], flower], c2w, K)
    assert not unrelated.judged and unrelated.flagged and "almost no matches" in unrelated.causes[0]


@needs_fern
def test_the_points_cache_keeps_the_check(tmp_path):
    images, c2w, K = fern_split()
    options = TriangulationOptions()
    said = []
    sparse, check = all_training_sparse_depth(images, c2w, K, options, None, tmp_path / "points.npz", said.append)
    again, cached = all_training_sparse_depth(images, c2w, K, options, None, tmp_path / "points.npz", said.append)
    assert isinstance(check, CameraCheck) and cached == check and again.num_points == sparse.num_points
    assert check.matches >= 100 and check.points <= check.matches and sparse.num_points >= 100
    assert not any("stale" in line or "corrupt" in line for line in said)


@needs_fern
def test_the_start_up_summary_of_a_fern_copy_with_the_wrong_focal_warns_once(tmp_path):
    from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
    from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
    from frugalnerf_ns.run.pipeline import camera_line

    copy = tmp_path / "fern"
    shutil.copytree(FERN / "images_8", copy / "images_8")
    rows = np.load(FERN / "poses_bounds.npy")
    rows[:, 14] *= 0.8  # the hwf column's focal length
    np.save(copy / "poses_bounds.npy", rows)

    def line(data: Path) -> str:
        config = FrugalDataManagerConfig(dataparser=LLFFDataParserConfig(data=data, train_views=(6, 13)),
                                         train_num_rays_per_batch=100, num_novel_rays_per_batch=40, patch_size=3,
                                         sparse_cache_dir=tmp_path / "cache")
        return camera_line(config.setup(device="cpu", test_mode="val"))

    warned = line(copy)
    assert warned.startswith("[bold yellow]") and "do not explain the training photos" in warned
    assert "the focal length: 1.2" in warned and "poses_bounds.npy's hwf column" in warned
    published = line(FERN)
    assert published.endswith(": they explain the photos") and "median reprojection error" in published


def test_the_user_pages_camera_table_is_the_records():
    import importlib.util
    import json

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("camera_check_table", root / "scripts" / "camera_check_table.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    record = json.loads((root / "docs" / "notes" / "camera_check.json").read_text())
    rows = script.page_table(record).splitlines()
    page = (root / "docs" / "data.md").read_text()
    assert len(rows) == 8 and all(row in page for row in rows)
    # The record's claim: every scene as published passes, every broken copy is flagged.
    for scene in record["scenes"].values():
        assert not scene["copies"]["as published"]["flagged"] and scene["copies"]["as published"]["judged"]
        assert all(copy["flagged"] for name, copy in scene["copies"].items() if name != "as published")
