"""Every layout round-trips: the parsed cameras see the fixture's 3D point at the pixels it was put at.

Parsers normalise the world (recentring, scaling, unit sphere), so the check is frame-free: rays through the
expected pixels of every camera must meet in one point in front of all of them. Axis-order or
OpenCV/OpenGL mistakes make them miss.
"""

from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.dataparsers.blender import BlenderDataParserConfig
from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
from frugalnerf_ns.data.dataparsers.nerfstudio_format import (
    FewShotColmapDataParserConfig,
    FewShotNerfstudioDataParserConfig,
)
from frugalnerf_ns.data.dataparsers.realestate import RealEstateDataParserConfig
from tests import layout_fixtures as fx

LAYOUTS = {
    "llff": (fx.write_llff, lambda d: LLFFDataParserConfig(data=d, downscale_factor=2, train_views=(1, 3, 5, 7, 9),
                                                            test_views=(0, 2, 4, 6, 8))),
    "llff principal point": (lambda d: fx.write_llff(d, principal_point=(44.0, 26.0)), lambda d: LLFFDataParserConfig(
        data=d, downscale_factor=2, principal_point=(44.0, 26.0), train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "llff photos only": (fx.write_llff_photos, lambda d: LLFFDataParserConfig(
        data=d, train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "dtu": (fx.write_dtu, lambda d: DTUDataParserConfig(data=d, train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "realestate": (fx.write_realestate, lambda d: RealEstateDataParserConfig(data=d, num_train_views=4, near_bound=1.0)),
    "colmap": (fx.write_colmap, lambda d: FewShotColmapDataParserConfig(
        data=d, colmap_path=Path("sparse/0"), train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "colmap photos only": (fx.write_colmap_photos, lambda d: FewShotColmapDataParserConfig(
        data=d, colmap_path=Path("sparse/0"), train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "nerfstudio": (fx.write_nerfstudio, lambda d: FewShotNerfstudioDataParserConfig(
        data=d, train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
    "instant-ngp capture": (fx.write_instant_ngp, lambda d: BlenderDataParserConfig(
        data=d, train_views=(1, 3, 5, 7, 9), test_views=(0, 2, 4, 6, 8))),
}


def all_views(config, pixels):
    """Cameras and expected pixels of the train and test splits together."""
    parser = config.setup()
    cams, pix = [], []
    for split in ("train", "test"):
        outputs = parser.get_dataparser_outputs(split)
        names = [p.name for p in outputs.image_filenames]
        cams.append(outputs.cameras)
        # Copies made into a cache hold only the splits parsed so far: name the views by the data's own folder.
        folder = outputs.image_filenames[0].parent
        if "frugalnerf_cache" in folder.parts:
            folder = Path(config.data) / "images"
        all_names = sorted(p.name for p in folder.iterdir())
        pix += [pixels[all_names.index(n)] for n in names]
    return cams, pix, outputs


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_parsed_cameras_see_the_point_where_the_fixture_put_it(layout, tmp_path):
    write, make_config = LAYOUTS[layout]
    pixels = write(tmp_path / layout)
    cams, pix, _ = all_views(make_config(tmp_path / layout), pixels)
    origins, dirs = [], []
    offset = 0
    for cameras in cams:
        o, d = fx.pixel_rays(cameras, pix[offset : offset + len(cameras)])
        origins.append(o)
        dirs.append(d)
        offset += len(cameras)
    origins, dirs = torch.cat(origins), torch.cat(dirs)
    scale = (origins - origins.mean(0)).norm(dim=-1).max()
    meeting = []
    for j in range(1, len(origins)):
        p, q, s, t = fx.closest_points(origins[0], dirs[0], origins[j], dirs[j])
        assert (p - q).norm() < 1e-4 * scale, f"{layout}: rays of views 0 and {j} miss each other"
        assert s > 0 and t > 0, f"{layout}: the point is behind a camera"
        meeting.append(p)
    meeting = torch.stack(meeting)
    assert (meeting - meeting.mean(0)).norm(dim=-1).max() < 1e-4 * scale


def test_llff_photos_only_train_on_copies_made_once_in_the_cache(tmp_path, capsys):
    scene = tmp_path / "capture"
    fx.write_llff_photos(scene)
    parse = LLFFDataParserConfig(data=scene, train_views=(1, 3), test_views=(0, 2)).setup().get_dataparser_outputs
    train = parse("train")
    said = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    assert "full-size photos only (1280x960): training at 1/2 (640x480)" in said and "making 2 image(s)" in said
    assert all(p.parent == scene / "frugalnerf_cache" / "images_2" for p in train.image_filenames)
    assert int(train.cameras.width[0, 0]) == 640 and int(train.cameras.height[0, 0]) == 480
    assert torch.allclose(train.cameras.fx[:, 0], torch.tensor([36.0 * 16] * 2))  # the fixture's 36 px at 40x30
    with Image.open(train.image_filenames[1]) as img:  # view 3's grey (10 * 3), area-averaged
        assert img.size == (640, 480) and np.asarray(img)[100, 200].tolist() == [30, 30, 30]
    stamp = train.image_filenames[0].stat().st_mtime_ns
    assert parse("train").image_filenames == train.image_filenames and "making" not in capsys.readouterr().out
    assert train.image_filenames[0].stat().st_mtime_ns == stamp  # reused, not rewritten
    # An explicit factor still rules, also where no images_<factor>/ exists.
    four = LLFFDataParserConfig(data=scene, downscale_factor=4, train_views=(1, 3)).setup().get_dataparser_outputs("train")
    assert int(four.cameras.width[0, 0]) == 320 and torch.allclose(four.cameras.fx[:, 0], torch.tensor([36.0 * 8] * 2))
    assert "training at 1/" not in capsys.readouterr().out


def test_a_read_only_capture_caches_its_copies_in_the_users_cache(tmp_path, monkeypatch, capsys):
    scene = tmp_path / "capture"
    fx.write_llff_photos(scene)
    for folder in (scene, scene / "images"):  # read-only as a dataset mount (root could still write: it must not)
        folder.chmod(0o555)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "user"))
    train = LLFFDataParserConfig(data=scene, train_views=(1, 3)).setup().get_dataparser_outputs("train")
    assert all(p.is_relative_to(tmp_path / "user" / "frugalnerf") and p.is_file() for p in train.image_filenames)
    said = " ".join(capsys.readouterr().out.split())  # the console wraps long lines
    assert said.count("cannot be written: its caches go to") == 1 and f"{scene} cannot be written" in said
    assert sorted(p.name for p in scene.iterdir()) == ["images", "poses_bounds.npy"]  # nothing written there
    for folder in (scene, scene / "images"):
        folder.chmod(0o755)  # so that pytest can remove it


def test_an_llff_capture_that_sweeps_around_gets_its_frame_from_the_training_cameras(tmp_path, capsys):
    from frugalnerf_ns.geometry.scene_analysis import viewing_directions

    def mean_direction(cameras):
        mean = viewing_directions(cameras.camera_to_worlds).mean(0)
        return (mean / mean.norm()).float()

    fx.write_llff(tmp_path / "sweep", forward_facing=False)
    train = LLFFDataParserConfig(data=tmp_path / "sweep", downscale_factor=2, train_views=(0, 1), test_views=(5, 9),
                                 ndc=False).setup().get_dataparser_outputs("train")
    # NDC looks along -z of the frame: the training cameras at one end of the arc look along it ...
    assert float(mean_direction(train.cameras) @ torch.tensor([0.0, 0.0, -1.0])) > 0.9998  # within ~1 degree
    assert "the frame is the training cameras' average camera" in " ".join(capsys.readouterr().out.split())
    # ... and a forward-facing capture keeps the paper's frame, the average of all its cameras.
    fx.write_llff(tmp_path / "forward")
    every = LLFFDataParserConfig(data=tmp_path / "forward", downscale_factor=2, train_views=(0, 1), test_views=(
        2, 3, 4, 5, 6, 7, 8, 9)).setup()
    cameras = [every.get_dataparser_outputs(split).cameras for split in ("train", "test")]
    joined = torch.cat([c.camera_to_worlds for c in cameras])
    assert float(mean_direction(type(cameras[0])(camera_to_worlds=joined, fx=1.0, fy=1.0, cx=1.0, cy=1.0)) @
                 torch.tensor([0.0, 0.0, -1.0])) > 0.99999
    assert "training cameras' average" not in capsys.readouterr().out


@pytest.mark.parametrize("forward_facing", [True, False])
def test_llff_records_its_scaling_and_recentring_as_the_dataparser_transform(tmp_path, forward_facing):
    """Poses mapped back with nerfstudio's own inverse land on poses_bounds.npy's cameras (OpenGL axes)."""
    import numpy as np

    from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl

    fx.write_llff(tmp_path / "scene", forward_facing=forward_facing)
    outputs = LLFFDataParserConfig(data=tmp_path / "scene", downscale_factor=2, train_views=(0, 1), test_views=(5, 9),
                                   ndc=False).setup().get_dataparser_outputs("train")
    rows = np.load(tmp_path / "scene" / "poses_bounds.npy")[:, :15].reshape(-1, 3, 5)
    expected = torch.from_numpy(llff_to_opengl(rows[:, :, :4])[[0, 1]]).float()
    back = outputs.transform_poses_to_original_space(outputs.cameras.camera_to_worlds, camera_convention="opengl")
    assert not torch.allclose(outputs.cameras.camera_to_worlds, expected, atol=1e-3)  # the model frame differs
    assert torch.allclose(back, expected, atol=1e-4)


def test_colmap_photos_are_read_from_the_cache_or_from_images_n_beside_them(tmp_path, capsys):
    scene = tmp_path / "colmap"
    fx.write_colmap_photos(scene)
    config = lambda **kw: FewShotColmapDataParserConfig(data=scene, colmap_path=Path("sparse/0"), **kw)  # noqa: E731
    train = config(train_views=(1, 3)).setup().get_dataparser_outputs("train")
    said = " ".join(capsys.readouterr().out.split())
    assert "1280x960 photos: training at 1/2 (640x480)" in said and "making 10 image(s)" in said
    assert all(p.parent == scene / "frugalnerf_cache" / "images_2" for p in train.image_filenames)
    assert int(train.cameras.width[0, 0]) == 640 and torch.allclose(train.cameras.fx[:, 0], torch.tensor([36.0 * 16] * 2))
    # A complete images_4/ beside images/ (as ns-process-data makes them) is read as it is.
    fx.write_images(scene / "images_4", [f"img_{i:03d}.png" for i in range(10)], size=(320, 240))
    four = config(train_views=(1, 3), downscale_factor=4).setup().get_dataparser_outputs("train")
    assert all(p.parent == scene / "images_4" for p in four.image_filenames)
    assert int(four.cameras.width[0, 0]) == 320 and torch.allclose(four.cameras.fx[:, 0], torch.tensor([36.0 * 8] * 2))


def test_dtu_intrinsics_are_scaled_to_the_loaded_images(tmp_path):
    fx.write_dtu(tmp_path / "dtu")
    outputs = DTUDataParserConfig(data=tmp_path / "dtu", train_views=(1, 3)).setup().get_dataparser_outputs("train")
    assert torch.allclose(outputs.cameras.fx[:, 0], torch.tensor([36.0, 36.0]), atol=1e-3)
    assert torch.allclose(outputs.cameras.cx[:, 0], torch.tensor([19.0, 19.0]), atol=1e-3)
    assert int(outputs.cameras.width[0, 0]) == fx.WIDTH


def test_dtu_test_split_carries_eval_masks_and_train_split_does_not(tmp_path):
    fx.write_dtu(tmp_path / "dtu")
    parser = DTUDataParserConfig(data=tmp_path / "dtu", train_views=(1, 3)).setup()
    assert "eval_mask_filenames" not in parser.get_dataparser_outputs("train").metadata
    test = parser.get_dataparser_outputs("test")
    assert [p.name for p in test.metadata["eval_mask_filenames"]] == ["000.png", "008.png"]


def test_an_llff_split_that_is_not_forward_facing_is_modelled_in_a_box_around_its_focus(tmp_path):
    """NDC only for forward-facing splits: a split from across the fixture's 80-degree arc gets a metric box
    centred where the cameras look, holding them, and a far background; --ndc True keeps NDC; a forward-facing
    split keeps NDC, and with --ndc False the baselines' box around the frusta (no far background)."""
    from frugalnerf_ns.geometry.scene_analysis import classify_camera_layout

    fx.write_llff(tmp_path / "sweep", forward_facing=False)

    def parse(train_views, split="train", **options):
        return LLFFDataParserConfig(data=tmp_path / "sweep", downscale_factor=2, train_views=train_views,
                                    test_views=(2, 6), **options).setup().get_dataparser_outputs(split)

    wide = parse((0, 4, 9))
    assert "ndc" not in wide.metadata and wide.metadata["far_background"] is True
    box, centres = wide.scene_box.aabb, wide.cameras.camera_to_worlds[:, :3, 3]
    focus = classify_camera_layout(wide.cameras.camera_to_worlds).focus
    assert torch.allclose((box[0] + box[1]) / 2, focus, atol=1e-4)
    sides = box[1] - box[0]
    assert torch.allclose(sides, sides[:1].expand(3)) and ((centres > box[0]) & (centres < box[1])).all()
    # ... not out to the far bound (12 here, 16 after scaling): the box's side is ~2.4 camera distances.
    assert float(sides[0]) < 2.5 * float((centres - focus).norm(dim=-1).max())
    far = float((centres - focus).norm(dim=-1).max())
    assert abs(float(sides[0]) - 2 * 1.2 * far) < 1e-3 * far
    smaller = parse((0, 4, 9), focus_box_scale=0.5).scene_box.aabb
    assert abs(float(smaller[1, 0] - smaller[0, 0]) - far) < 1e-3 * far
    with pytest.raises(DataError, match="--focus-box-scale must be positive"):
        parse((0, 4, 9), focus_box_scale=0.0)
    test = parse((0, 4, 9), split="test")
    assert torch.equal(test.scene_box.aabb, box) and test.metadata["far_background"] is True
    assert "ndc" in parse((0, 4, 9), ndc=True).metadata
    narrow = parse((0, 1))
    assert "ndc" in narrow.metadata and "far_background" not in narrow.metadata
    frusta = parse((0, 1), ndc=False)
    assert "ndc" not in frusta.metadata and "far_background" not in frusta.metadata
    assert float((frusta.scene_box.aabb[1] - frusta.scene_box.aabb[0]).max()) > 10.0  # out to the far bound


def test_llff_ndc_metadata_and_box(tmp_path):
    fx.write_llff(tmp_path / "llff")
    outputs = LLFFDataParserConfig(data=tmp_path / "llff", downscale_factor=2).setup().get_dataparser_outputs("train")
    ndc = outputs.metadata["ndc"]
    assert ndc["width"] == fx.WIDTH and ndc["height"] == fx.HEIGHT and abs(ndc["focal"] - 36.0) < 1e-6
    assert torch.allclose(outputs.scene_box.aabb, torch.tensor([[-1.5, -1.67, -1.0], [1.5, 1.67, 1.0]]))
    # The nearest bound is scaled to 1 / 0.75, in front of NDC's near plane at 1.
    assert abs(outputs.metadata["near_far"][0] - 1 / 0.75) < 1e-6
    # Recentred: the mean camera looks down -z.
    c2w = outputs.cameras.camera_to_worlds
    assert (c2w[:, 2, 2] > 0.9).all()


@pytest.mark.parametrize("layout", sorted(LAYOUTS))
def test_auto_detects_each_layout(layout, tmp_path):
    LAYOUTS[layout][0](tmp_path / layout)
    name, config_type = detect_layout(tmp_path / layout)
    assert config_type is type(LAYOUTS[layout][1](tmp_path))
    factor = 2 if layout.startswith("llff") and "photos" not in layout else None  # the fixture writes images_2/
    near = 1.0 if layout == "realestate" else None  # flat frames: no points to find it from
    outputs = AutoDataParserConfig(data=tmp_path / layout, downscale_factor=factor, near_bound=near).setup() \
        .get_dataparser_outputs("train")
    assert len(outputs.image_filenames) >= 2


def test_auto_names_the_layouts_it_looked_for(tmp_path):
    fx.write_images(tmp_path / "x" / "pics", ["a.png", "b.png"])
    with pytest.raises(DataError) as err:
        detect_layout(tmp_path / "x")
    message = str(err.value)
    for needle in ("2 images, none where a layout reads them", "LLFF", "DTU", "RealEstate", "transforms.json", "COLMAP",
                   "photos without cameras: JPEG/PNG photos in the folder or in images/"):
        assert needle in message


def test_auto_passes_few_shot_options_on(tmp_path):
    fx.write_llff(tmp_path / "llff")
    config = AutoDataParserConfig(data=tmp_path / "llff", downscale_factor=2, train_views=(2, 5))
    outputs = config.setup().get_dataparser_outputs("train")
    assert [p.name for p in outputs.image_filenames] == ["image002.png", "image005.png"]


# ---- bad input ----------------------------------------------------------------------------------------------
def llff_scene(tmp_path):
    fx.write_llff(tmp_path / "llff")
    return tmp_path / "llff"


def parse_llff(scene, split="train"):
    return LLFFDataParserConfig(data=scene, downscale_factor=2).setup().get_dataparser_outputs(split)


def test_truncated_poses_bounds(tmp_path):
    scene = llff_scene(tmp_path)
    data = (scene / "poses_bounds.npy").read_bytes()
    (scene / "poses_bounds.npy").write_bytes(data[: len(data) // 2])
    with pytest.raises(DataError, match="poses_bounds.npy is unreadable or truncated"):
        parse_llff(scene)


def test_wrong_poses_bounds_shape(tmp_path):
    scene = llff_scene(tmp_path)
    np.save(scene / "poses_bounds.npy", np.ones((10, 15)))
    with pytest.raises(DataError, match=r"shape \(10, 15\).*N x 17"):
        parse_llff(scene)


def test_image_count_must_match_pose_count(tmp_path):
    scene = llff_scene(tmp_path)
    (scene / "images_2" / "image009.png").unlink()
    with pytest.raises(DataError, match="10 poses but .*images_2 has 9 images"):
        parse_llff(scene)


def test_nan_pose_names_the_row(tmp_path):
    scene = llff_scene(tmp_path)
    rows = np.load(scene / "poses_bounds.npy")
    rows[4, 3] = np.nan
    np.save(scene / "poses_bounds.npy", rows)
    with pytest.raises(DataError, match=r"row\(s\) \[4\] contain NaN"):
        parse_llff(scene)


def test_unreadable_image_names_the_file(tmp_path):
    scene = llff_scene(tmp_path)
    (scene / "images_2" / "image001.png").write_bytes(b"not a png")
    with pytest.raises(DataError, match="image001.png is unreadable or corrupt"):
        LLFFDataParserConfig(data=scene, downscale_factor=2, train_views=(1, 3)).setup().get_dataparser_outputs("train")


def test_missing_images_folder_and_bad_view(tmp_path):
    scene = llff_scene(tmp_path)
    with pytest.raises(DataError, match="images_8 not found"):
        LLFFDataParserConfig(data=scene).setup().get_dataparser_outputs("train")
    with pytest.raises(DataError, match=r"train view\(s\) \[12\] do not exist"):
        LLFFDataParserConfig(data=scene, downscale_factor=2, train_views=(1, 12)).setup().get_dataparser_outputs("train")


def test_realestate_rows_must_match_frames(tmp_path):
    fx.write_realestate(tmp_path / "re", count=12)
    rows = np.loadtxt(tmp_path / "re" / "CameraExtrinsics.csv", delimiter=",")
    np.savetxt(tmp_path / "re" / "CameraExtrinsics.csv", rows[:-1], delimiter=",")
    with pytest.raises(DataError, match="12 frames in rgb/ but 12 intrinsics and 11 extrinsics rows"):
        RealEstateDataParserConfig(data=tmp_path / "re").setup().get_dataparser_outputs("train")


def test_nerfstudio_few_shot_conflicts_with_its_own_split_lists(tmp_path, procedural_scene):
    with pytest.raises(DataError, match="defines its own split"):
        FewShotNerfstudioDataParserConfig(data=procedural_scene, num_train_views=2).setup().get_dataparser_outputs()
    # Without few-shot options the file's own split is used.
    outputs = FewShotNerfstudioDataParserConfig(data=procedural_scene).setup().get_dataparser_outputs("train")
    assert len(outputs.image_filenames) == 3


def test_datamanager_puts_eval_masks_in_test_batches_only(tmp_path):
    from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
    from frugalnerf_ns.data.dataset import FrugalDataset

    fx.write_dtu(tmp_path / "dtu")
    config = FrugalDataManagerConfig(dataparser=DTUDataParserConfig(data=tmp_path / "dtu", train_views=(1, 3)))
    manager = config.setup(device="cpu", test_mode="test")
    assert isinstance(manager.eval_dataset, FrugalDataset)
    mask = manager.eval_dataset[0]["eval_mask"]
    assert mask.shape == (fx.HEIGHT, fx.WIDTH, 1) and mask.dtype == torch.bool
    assert int(mask.sum()) == 15 * 20  # the fixture's mask rectangle
    assert "eval_mask" not in manager.train_dataset[0]


def test_dtu_test_split_marks_regnerfs_25_views_among_pixelnerfs_40(tmp_path):
    fx.write_dtu(tmp_path / "dtu", count=49)
    parser = DTUDataParserConfig(data=tmp_path / "dtu").setup()
    outputs = parser.get_dataparser_outputs("test")
    names = [int(p.stem) for p in outputs.image_filenames]
    assert len(names) == 40
    regnerf = [names[n] for n in outputs.metadata["test_subsets"]["regnerf25"]]
    assert len(regnerf) == 25
    dropped = set(names) - set(regnerf)
    assert dropped == {3, 4, 5, 6, 7, 16, 17, 18, 19, 20, 21, 36, 37, 38, 39}
    # The training split and explicit test views carry no published subset.
    assert "test_subsets" not in parser.get_dataparser_outputs("train").metadata
    explicit = DTUDataParserConfig(data=tmp_path / "dtu", test_views=(1, 2, 3)).setup()
    assert "test_subsets" not in explicit.get_dataparser_outputs("test").metadata


def test_eval_masks_are_read_for_nerfstudios_own_dataset_too(tmp_path):
    """tensorf's datamanager builds a plain InputDataset, which ignores eval masks; the offline evaluator
    reads them with ``read_eval_mask`` so baselines are scored on the same pixels."""
    from nerfstudio.data.datasets.base_dataset import InputDataset

    from frugalnerf_ns.data.dataset import FrugalDataset, read_eval_mask

    fx.write_dtu(tmp_path / "dtu")
    outputs = DTUDataParserConfig(data=tmp_path / "dtu", train_views=(1, 3)).setup().get_dataparser_outputs("test")
    plain = InputDataset(outputs)
    assert "eval_mask" not in plain[0]
    mask = read_eval_mask(plain, 0)
    assert mask.shape == (fx.HEIGHT, fx.WIDTH, 1) and mask.dtype == torch.bool
    assert mask[5:20, 10:30].all() and int(mask.sum()) == 15 * 20  # the fixture's object rectangle
    assert torch.equal(FrugalDataset(outputs)[0]["eval_mask"], mask)
    train = DTUDataParserConfig(data=tmp_path / "dtu", train_views=(1, 3)).setup().get_dataparser_outputs("train")
    assert read_eval_mask(InputDataset(train), 0) is None
