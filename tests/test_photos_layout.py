"""A folder of photos without cameras (issue 33): detected by frugal-auto, cameras estimated once and cached,
EXIF orientation and focal length honoured, test photos registered, the estimate's points used as the sparse
depth, one-line errors; and a short training run on it."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.dataparsers import photos as photos_module
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.photo_poses import focal_from_35mm
from frugalnerf_ns.geometry.reprojection import project_to_camera
from tests.photo_scene import TRUE, camera, render, write_photos
from tests.training_helpers import ns_train_main, preset_config, train

EXIF_ORIENTATION = 0x0112


def outputs(data: Path, **options):
    parser = AutoDataParserConfig(data=data, **options).setup()
    return parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")


def test_a_folder_of_photos_is_read_with_estimated_cameras_cached_once(tmp_path, monkeypatch):
    data = write_photos(tmp_path / "scene", TRUE)  # photos 0-2 train, 3 is the test photo
    assert detect_layout(data)[0] == "photos without cameras"
    train, test = outputs(data, test_views=(3,))
    assert len(train.image_filenames) == 3 and len(test.image_filenames) == 1
    assert train.metadata["ndc"]["focal"] == pytest.approx(float(train.cameras.fx[0]))
    # The frame: the nearest point at 1 / 0.75 of the unit the cameras move in (LLFF's rule), NDC along the
    # photos' mean camera.
    assert train.metadata["near_far"][0] == pytest.approx(1.0 / 0.75)
    assert torch.allclose(train.cameras.camera_to_worlds[:, :3, 2].mean(0), torch.tensor([0.0, 0.0, 1.0]), atol=0.05)
    # The estimate's points, in the outputs' frame, project to their pixels through the training cameras, and
    # their depths are distances in that frame.
    sparse = train.metadata["sparse_depth"]
    c2w = train.cameras.camera_to_worlds.double()[sparse.view]
    intrinsics = torch.tensor([[float(train.cameras.fx[0]), float(train.cameras.fy[0]), 160.0, 120.0]],
                              dtype=torch.float64).expand(len(sparse.view), 4)
    proj = project_to_camera(sparse.points[sparse.point], c2w, intrinsics)
    assert torch.allclose(proj.pixels, sparse.pixels, atol=1e-3)
    assert torch.allclose((sparse.points[sparse.point] - c2w[:, :, 3]).norm(dim=-1), sparse.depth, rtol=1e-4)
    # The test photo sits where the true camera is relative to the training ones (similarity-free check: the
    # ratio of its distance to camera 0 over the first baseline).
    centres = train.cameras.camera_to_worlds[:, :3, 3].double()
    test_centre = test.cameras.camera_to_worlds[0, :3, 3].double()
    truth = [c[:3, 3] for c in TRUE]
    expected = (truth[3] - truth[0]).norm() / (truth[1] - truth[0]).norm()
    assert float((test_centre - centres[0]).norm() / (centres[1] - centres[0]).norm()) == pytest.approx(float(expected), rel=0.03)
    cached = sorted((data / "frugalnerf_cache").glob("photo_cameras_*.npz"))
    assert len(cached) == 1

    def no_second_estimate(*args, **kwargs):
        raise AssertionError("cameras estimated again although the cache holds them")

    monkeypatch.setattr(photos_module, "estimate_cameras", no_second_estimate)
    again, again_test = outputs(data, test_views=(3,))
    assert torch.equal(again.cameras.camera_to_worlds, train.cameras.camera_to_worlds)
    assert torch.equal(again_test.cameras.camera_to_worlds, test.cameras.camera_to_worlds)
    # Other training photos are another estimate.
    with pytest.raises(AssertionError, match="estimated again"):
        outputs(data, train_views=(0, 1), test_views=(3,))


def test_photos_from_wide_apart_are_modelled_as_posed_llff_scenes_are(tmp_path):
    """Three photos 21 degrees either side of their mean direction (not forward-facing): the space LLFF's rule
    gives posed data (a metric box on their focus, a far background beyond), not NDC; and the estimate's points
    beyond the box place the far background's sphere and stay for L_sd, as triangulated ones do."""
    from frugalnerf_ns.data.dataparsers.llff import scene_space
    from frugalnerf_ns.data.dataparsers.photos import PhotosDataParserConfig
    from frugalnerf_ns.data.training_views import training_view_points
    from frugalnerf_ns.geometry.scene_analysis import FOCUS_BOX_SCALE

    def parse(**options):
        return PhotosDataParserConfig(data=data, **options).setup().get_dataparser_outputs("train")

    wide = [camera((x, 0.1 * i, 0.0), target=(0.0, 0.0, -1.8)) for i, x in enumerate((-0.7, 0.0, 0.7))]
    data = write_photos(tmp_path / "wide", wide)
    train = parse()
    assert "ndc" not in train.metadata and train.metadata["far_background"] is True
    c2w = train.cameras.camera_to_worlds
    box = train.scene_box.aabb
    assert bool(((c2w[:, :, 3] > box[0]) & (c2w[:, :, 3] < box[1])).all())  # the cameras stand inside it
    ndc, same = scene_space(c2w.double().numpy(), None, FOCUS_BOX_SCALE)
    assert not ndc and torch.allclose(box, same)
    assert parse(ndc=True).metadata["ndc"]["focal"] == pytest.approx(float(train.cameras.fx[0]))
    # frugal-auto (the default parser) carries both options to the layout it detects.
    forced, _ = outputs(data, ndc=True)
    assert forced.metadata["ndc"]["focal"] == pytest.approx(float(train.cameras.fx[0]))
    assert torch.allclose(outputs(data, focus_box_scale=0.6)[0].scene_box.aabb, parse(focus_box_scale=0.6).scene_box.aabb)
    with pytest.raises(DataError, match="--focus-box-scale must be positive"):
        parse(focus_box_scale=0.0)

    # A box half as wide leaves the wall behind the card beyond it.
    small = parse(focus_box_scale=0.6)
    sparse, box = small.metadata["sparse_depth"], small.scene_box.aabb
    beyond = ~((sparse.points >= box[0].double()) & (sparse.points <= box[1].double())).all(dim=-1)
    assert int(beyond.sum()) >= 20 and int((~beyond).sum()) >= 20
    # The estimate's points need no images, intrinsics, options or cache (no second triangulation).
    kept, shell, counts = training_view_points(small, small.cameras, None, None, None, 5, tmp_path / "unused.npz", "cpu", True)
    assert kept.num_points == sparse.num_points and shell is not None
    assert counts == (int(beyond.sum()), sparse.num_points)
    centre = box.mean(dim=0).double()
    assert shell[1] == pytest.approx(float((sparse.points[beyond] - centre).norm(dim=-1).median()), rel=1e-5)
    inside, none, _ = training_view_points(small, small.cameras, None, None, None, 5, tmp_path / "unused.npz", "cpu", False)
    assert none is None and inside.num_points == int((~beyond).sum())
    assert not (tmp_path / "unused.npz").exists()


def test_exif_orientation_and_focal_length_are_honoured(tmp_path):
    # Stored turned by 90 degrees with orientation 6 ("rotate 90 clockwise to view"): read upright.
    exif = Image.Exif()
    exif[EXIF_ORIENTATION] = 6
    exif.get_ifd(photos_module.EXIF_IFD)[photos_module.EXIF_FOCAL_35MM] = 30
    data = tmp_path / "turned"
    data.mkdir()
    for i, c2w in enumerate(TRUE[:2]):
        Image.fromarray(render(c2w)).transpose(Image.Transpose.ROTATE_90).save(data / f"p{i}.png", exif=exif)
    assert photos_module.upright_size_and_focal_35mm(data / "p0.png") == (320, 240, 30.0)
    train, test = outputs(data)
    upright = np.asarray(Image.open(train.image_filenames[0]).convert("RGB"))
    assert np.array_equal(upright, render(TRUE[0]))
    # Two photos: the focal length is EXIF's, not refined.
    assert float(train.cameras.fx[0]) == pytest.approx(focal_from_35mm(320, 240, 30.0))
    # No test photos: evaluation reads the training photos.
    assert test.image_filenames == train.image_filenames


def test_bad_photo_folders_get_one_line(tmp_path):
    one = write_photos(tmp_path / "one", TRUE[:1])
    with pytest.raises(DataError, match="1 training photo"):
        outputs(one)
    mixed = write_photos(tmp_path / "mixed", TRUE[:2])
    Image.fromarray(render(TRUE[2])[:200]).save(mixed / "photo_9.png")
    with pytest.raises(DataError, match="different sizes .*320x200, 320x240"):
        outputs(mixed)
    with pytest.raises(DataError, match="both training and test"):
        outputs(write_photos(tmp_path / "three", TRUE[:3]), train_views=(0, 1), test_views=(1,))


def test_blank_images_stop_ns_train_with_one_line(tmp_path):
    folder = tmp_path / "scene" / "images"
    folder.mkdir(parents=True)
    for i in range(3):
        Image.fromarray(np.full((48, 64, 3), 40 * i, dtype=np.uint8)).save(folder / f"img_{i}.png")
    said = ns_train_main(preset_config("frugalnerf-tiny", tmp_path / "scene", tmp_path / "out"))
    assert said.startswith("frugalnerf: error:") and "photo img_0.png has 0 SIFT features" in said
    assert not list((tmp_path / "scene").rglob("photo_cameras_*"))  # nothing half-estimated is cached


def test_training_on_photos_uses_the_estimated_points(tmp_path):
    data = write_photos(tmp_path / "scene", TRUE)
    config = preset_config("frugalnerf-tiny", data, tmp_path / "out", max_num_iterations=30)
    config.pipeline.datamanager.dataparser.test_views = (3,)
    trainer = train(config)
    manager = trainer.pipeline.datamanager
    estimated = manager.train_dataparser_outputs.metadata["sparse_depth"]
    assert manager.sparse is not None and manager.sparse.num_points == estimated.num_points
    # The registered test photo is scored like any test view.
    metrics, _ = trainer.pipeline.get_eval_image_metrics_and_images(step=30)
    assert math.isfinite(metrics["psnr"])
    assert sorted((tmp_path / "out").rglob("step-*.ckpt"))
    # Photos without cameras end their training with where the next photo would help most.
    suggestion = json.loads((trainer.base_dir / "next_view.json").read_text())
    assert len(suggestion["suggestions"]) == 3 and (trainer.base_dir / "next_view.png").is_file()
    assert (data / "camera_paths" / "next_view.json").is_file()  # where the viewer's render panel looks


def test_focal_length_options_reach_the_estimate_through_frugal_auto(tmp_path):
    from frugalnerf_ns.data.photo_poses import PoseEstimationOptions, focal_from_field_of_view

    data = write_photos(tmp_path / "scene", TRUE[:3])
    # Three photos without EXIF: the 65-degree guess (251 px) refined to the photos' true focal length.
    refined, _ = outputs(data)
    assert float(refined.cameras.fx[0]) == pytest.approx(280.0, rel=0.03)
    assumed, _ = outputs(data, poses=PoseEstimationOptions(refine_focal_length=False))
    assert float(assumed.cameras.fx[0]) == pytest.approx(focal_from_field_of_view(320, 240, 65.0))
    wider, _ = outputs(data, poses=PoseEstimationOptions(field_of_view=80.0, refine_focal_length=False))
    assert float(wider.cameras.fx[0]) == pytest.approx(focal_from_field_of_view(320, 240, 80.0))
