"""NeRF-synthetic (Blender) scenes: layout detection, the DietNeRF / FreeNeRF split, half resolution, RGBA on
white, cameras, and what the datamanager and model make of the scene. The fixture is the procedural scene
written in this layout (cameras all around the object, RGBA frames)."""

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.dataparsers.blender import BlenderDataParserConfig
from frugalnerf_ns.data.downscaled_images import area_downscale
from frugalnerf_ns.data.procedural_scene import SceneSpec, blender_camera_poses, render_view, write_blender_scene
from frugalnerf_ns.data.splits import dietnerf_train_views, load_split_table

SPEC = SceneSpec(width=64, height=64, focal=70.0)


@pytest.fixture(scope="module")
def blender_scene(tmp_path_factory) -> Path:
    return write_blender_scene(tmp_path_factory.mktemp("data") / "blender", SPEC, counts=(12, 2, 16))


def outputs(scene: Path, split: str = "train", **options):
    return AutoDataParserConfig(data=scene, **options).setup().get_dataparser_outputs(split)


def test_the_published_eight_views_are_dietnerfs_seeded_draw():
    table = load_split_table()["blender"]
    assert table["num_train_views"] == 8 and table["test_every"] == 8
    # The ids other few-shot loaders hard-code come out of DietNeRF's rule (numpy seed 0, choice of 8 of 100).
    assert table["train_views"][8] == dietnerf_train_views(100, 8) == [26, 86, 2, 55, 75, 93, 16, 73]
    assert dietnerf_train_views(100, 4) == [26, 86, 2, 55]  # the same draw, shorter


def test_frugal_auto_detects_the_layout_and_applies_the_protocol(blender_scene):
    name, config_type = detect_layout(blender_scene)
    assert "Blender" in name and config_type is BlenderDataParserConfig
    train = outputs(blender_scene)
    # 8 training views by the seeded draw over the 12 training frames; indices are JSON frame positions.
    assert [p.name for p in train.image_filenames] == [f"r_{i}.png" for i in dietnerf_train_views(12, 8)]
    test = outputs(blender_scene, "test")
    assert [p.name for p in test.image_filenames] == ["r_0.png", "r_8.png"]  # every 8th test frame
    assert all("/test/" in str(p) for p in test.image_filenames)
    assert train.metadata["near_far"] == (2.0, 6.0)
    assert torch.equal(train.scene_box.aabb, torch.tensor([[-1.5] * 3, [1.5] * 3]))


def test_few_shot_options_choose_views(blender_scene):
    train = outputs(blender_scene, train_views=(3, 10))
    assert [p.name for p in train.image_filenames] == ["r_3.png", "r_10.png"]
    assert len(outputs(blender_scene, num_train_views=3).image_filenames) == 3
    test = outputs(blender_scene, "test", test_views=(1, 2, 15))
    assert [p.name for p in test.image_filenames] == ["r_1.png", "r_2.png", "r_15.png"]


@pytest.mark.parametrize("options,words", [
    (dict(train_views=(3, 12)), ["transforms_train.json", "12", "0..11"]),
    (dict(num_train_views=13), ["transforms_train.json", "13", "12 frames"]),
    (dict(test_views=(16,)), ["transforms_test.json", "16"]),
])
def test_views_that_do_not_exist_are_one_clear_error(blender_scene, options, words):
    split = "test" if "test_views" in options else "train"
    with pytest.raises(DataError) as err:
        outputs(blender_scene, split, **options)
    message = str(err.value)
    assert "\n" not in message and all(w in message for w in words), message


def test_cameras_look_at_the_object_centre_with_the_file_focal(blender_scene):
    train = outputs(blender_scene)
    cameras = train.cameras
    assert torch.allclose(cameras.fx, torch.full_like(cameras.fx, SPEC.focal), atol=1e-3)
    assert float(cameras.cx[0]) == SPEC.width / 2 and int(cameras.width[0]) == SPEC.width
    # The ray through each image centre passes through the point every camera was aimed at.
    centre = torch.tensor([[SPEC.height / 2, SPEC.width / 2]])
    target = torch.tensor([0.0, 0.0, 0.25])
    for i in range(len(cameras)):
        ray = cameras.generate_rays(camera_indices=torch.tensor([[i]]), coords=centre)
        offset = target - ray.origins[0]
        miss = (offset - (offset @ ray.directions[0]) * ray.directions[0]).norm()
        assert float(miss) < 1e-3


def test_rgba_frames_keep_alpha_and_composite_to_the_white_render(blender_scene):
    frame = np.asarray(Image.open(blender_scene / "train" / "r_0.png"), dtype=np.float64) / 255.0
    assert frame.shape == (SPEC.height, SPEC.width, 4)
    alpha = frame[..., 3:]
    assert 0.05 < alpha.mean() < 0.95  # object and transparent background both present
    c2w = blender_camera_poses(12, SPEC.radius, seed=0)[0]
    on_white = render_view(c2w, SPEC).numpy()
    composited = frame[..., :3] * alpha + (1.0 - alpha)
    assert np.abs(composited - on_white).max() < 2.5 / 255.0


def test_half_resolution_averages_2x2_blocks_and_halves_the_focal(blender_scene):
    train = outputs(blender_scene, downscale_factor=2, train_views=(0, 5))
    assert int(train.cameras.width[0]) == SPEC.width // 2 and int(train.cameras.height[0]) == SPEC.height // 2
    assert torch.allclose(train.cameras.fx, torch.full_like(train.cameras.fx, SPEC.focal / 2), atol=1e-3)
    small = np.asarray(Image.open(train.image_filenames[1]), dtype=np.float64)
    full = np.asarray(Image.open(blender_scene / "train" / "r_5.png"), dtype=np.float64)
    # Straight (not premultiplied) alpha, channel by channel, as cv2.resize(INTER_AREA) in the protocol.
    expected = full.reshape(SPEC.height // 2, 2, SPEC.width // 2, 2, 4).mean(axis=(1, 3))
    assert small.shape == expected.shape and np.abs(small - expected).max() <= 0.5 + 1e-9
    # Written once next to the data, then reused.
    assert train.image_filenames[1].is_relative_to(blender_scene / "frugalnerf_cache")
    stamp = train.image_filenames[1].stat().st_mtime_ns
    again = outputs(blender_scene, downscale_factor=2, train_views=(0, 5))
    assert again.image_filenames[1].stat().st_mtime_ns == stamp


def test_area_downscale_drops_partial_blocks():
    pixels = np.arange(5 * 7 * 4, dtype=np.uint8).reshape(5, 7, 4)
    small = area_downscale(pixels, 2)
    assert small.shape == (2, 3, 4)
    assert small[0, 0, 0] == round(np.mean([pixels[0, 0, 0], pixels[0, 1, 0], pixels[1, 0, 0], pixels[1, 1, 0]]))


def test_unwritable_data_gets_its_half_resolution_images_in_the_users_cache(blender_scene, tmp_path, monkeypatch, capsys):
    scene = tmp_path / "readonly"
    shutil.copytree(blender_scene, scene, ignore=shutil.ignore_patterns("frugalnerf_cache"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user"))
    # A file where the cache folder would go: no folder can be made there (also for root, unlike chmod).
    (scene / "frugalnerf_cache").write_text("not a folder")
    train = outputs(scene, downscale_factor=2, train_views=(1, 2))
    assert (scene / "frugalnerf_cache").is_file()
    assert all(Path(p).is_relative_to(tmp_path / "user" / "frugalnerf") for p in train.image_filenames)
    assert all(Path(p).is_file() and Image.open(p).size == (SPEC.width // 2, SPEC.height // 2) for p in train.image_filenames)
    said = capsys.readouterr().out
    assert said.count("cannot be written: its caches go to") == 1 and "making 2 image(s) at 1/2 size" in said
    again = outputs(scene, downscale_factor=2, train_views=(1, 2))  # made once: the second parse reuses them
    assert again.image_filenames == train.image_filenames and "making" not in capsys.readouterr().out


@pytest.mark.parametrize("break_it,words", [
    (lambda m: m.pop("camera_angle_x"), ["transforms_train.json", "camera_angle_x"]),
    (lambda m: m["frames"][3].update(transform_matrix=[[1, 0], [0, 1]]), ["transforms_train.json", "frame 3", "4x4"]),
    (lambda m: m["frames"][3].update(file_path="./train/missing"), ["missing.png", "not found"]),
])
def test_broken_transforms_are_one_clear_error(blender_scene, tmp_path, break_it, words):
    scene = tmp_path / "broken"
    shutil.copytree(blender_scene, scene, ignore=shutil.ignore_patterns("frugalnerf_cache"))
    meta = json.loads((scene / "transforms_train.json").read_text())
    break_it(meta)
    (scene / "transforms_train.json").write_text(json.dumps(meta))
    with pytest.raises(DataError) as err:
        outputs(scene, train_views=(3, 4))
    assert "\n" not in str(err.value) and all(w in str(err.value) for w in words), str(err.value)


def test_the_datamanager_calls_it_an_object_with_occlusion_and_novel_poses_around_it(blender_scene, tmp_path):
    config = FrugalDataManagerConfig(
        dataparser=AutoDataParserConfig(data=blender_scene), train_num_rays_per_batch=100,
        num_novel_rays_per_batch=40, patch_size=3, sparse_cache_dir=tmp_path,
    )
    manager = config.setup(device="cpu", test_mode="val")
    assert manager.train_images.shape[-1] == 4  # alpha kept for the loss's random background
    # The 8 cameras surround the object (they would make a 360 capture without the transparent background).
    assert manager.scene_layout.coverage_degrees >= 180.0
    assert manager.scene_type == "object"
    # Novel poses: one turn around the object at the cameras' distance, not a spiral around their mean pose
    # (which sits inside the object).
    centers = manager.novel_cameras.camera_to_worlds[:, :3, 3]
    train_centers = manager.train_dataset.cameras.camera_to_worlds[:, :3, 3]
    focus = manager.scene_layout.focus
    distance = (centers - focus).norm(dim=-1)
    assert float(distance.min()) > 0.7 * float((train_centers - focus).norm(dim=-1).min())
    azimuth = torch.atan2(centers[:, 1] - focus[1], centers[:, 0] - focus[0])
    assert float(azimuth.max() - azimuth.min()) > math.radians(300)
    forward = -manager.novel_cameras.camera_to_worlds[:, :3, 2]
    to_focus = torch.nn.functional.normalize(focus - centers, dim=-1)
    assert float((forward * to_focus).sum(-1).min()) > 0.999
    from tests.helpers import model_for

    model = model_for(manager, occlusion_weight=0.01)
    assert model.scene_type == "object" and model.occlusion_active


def test_startup_benchmark_times_every_stage_and_writes_json(blender_scene, tmp_path, capsys):
    from frugalnerf_ns.bench import startup as script

    out = tmp_path / "startup.json"
    script.main(["--data", str(blender_scene), "--views", "2", "10", "--all-pairs-up-to", "10", "--out", str(out)])
    rows = json.loads(out.read_text())["rows"]
    assert [r["views"] for r in rows] == [2, 10]
    # The old way matched all 45 pairs of 10 views (pair growth is tested in test_sparse_points).
    assert rows[0]["pairs"] == 1 and rows[1]["pairs"] <= 45 and rows[1]["before_pairs"] == 45
    for row in rows:
        assert all(row[k] > 0 for k in ("parse_s", "load_s", "sift_s", "match_s", "triangulate_s"))
        assert abs(row["total_s"] - sum(row[k] for k in ("parse_s", "load_s", "sift_s", "match_s", "triangulate_s"))) < 1e-9
        assert row["width"] == SPEC.width
    printed = capsys.readouterr().out
    assert "| views |" in printed and "| 10 |" in printed
    with pytest.raises(SystemExit) as bad:
        script.main(["--data", str(blender_scene), "--views", "40", "--out", str(out)])
    assert str(bad.value.code).startswith("benchmark_startup:") and "40" in str(bad.value.code)


def test_800_pixel_frames_are_halved_to_the_protocols_400_by_default(tmp_path):
    spec = SceneSpec(width=800, height=800, focal=1111.1, supersample=1)
    scene = write_blender_scene(tmp_path / "full", spec, counts=(2, 1, 1))
    train = outputs(scene, train_views=(0, 1))
    assert {Image.open(p).size for p in train.image_filenames} == {(400, 400)}
    assert int(train.cameras.width[0]) == 400 and abs(float(train.cameras.fx[0]) - 1111.1 / 2) < 1e-2
    test = outputs(scene, "test")
    assert Image.open(test.image_filenames[0]).size == (400, 400)


def test_unreadable_json_is_one_clear_error(blender_scene, tmp_path):
    scene = tmp_path / "badjson"
    shutil.copytree(blender_scene, scene, ignore=shutil.ignore_patterns("frugalnerf_cache"))
    (scene / "transforms_test.json").write_text('{"camera_angle_x": 0.7, "frames": [')
    with pytest.raises(DataError) as err:
        outputs(scene, "test")
    assert "\n" not in str(err.value) and "transforms_test.json" in str(err.value) and "JSON" in str(err.value)
