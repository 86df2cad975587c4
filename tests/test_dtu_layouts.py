"""DTU in MonoSDF's layout (``000000_rgb.png`` centre crops, cameras for the whole frame), made here from scan65
(skipped where ../shared/data is absent), read against the uncropped scene; cameras that fit no reading of their
images stop with one line."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig, fit_to_images
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.sparse_points import TriangulationOptions, triangulate_training_views

SCAN65 = Path(__file__).resolve().parents[2] / "shared" / "data" / "dtu" / "scan65"
needs_dtu = pytest.mark.skipif(not SCAN65.is_dir(), reason=f"real DTU scene not present at {SCAN65}")
CROP = 384  # MonoSDF's side: the frame's middle 1200x1200 of 1600x1200; here the middle 300x300 of the 400x300 images


def monosdf_copy(folder: Path, masks: bool) -> Path:
    """scan65 as MonoSDF stores DTU: centre crops at 384x384 named 000000_rgb.png, cameras.npz for the full frame."""
    folder.mkdir(parents=True)
    # The camera file the uncropped scene is read with (its first of CAMERA_FILES), under MonoSDF's name.
    shutil.copy(SCAN65 / "cameras_sphere.npz", folder / "cameras.npz")
    for path in sorted((SCAN65 / "image").glob("*.png")):
        with Image.open(path) as image:
            crop = image.convert("RGB").crop((50, 0, 350, 300)).resize((CROP, CROP), Image.BICUBIC)
        crop.save(folder / f"{path.stem}_rgb.png")
    if masks:
        (folder / "mask").mkdir()
        for path in sorted((SCAN65 / "mask").glob("*.png")):
            with Image.open(path) as mask:
                mask.crop((50, 0, 350, 300)).resize((CROP, CROP), Image.NEAREST).save(folder / "mask" / path.name)
    return folder


@pytest.fixture(scope="module")
def cropped(tmp_path_factory):
    if not SCAN65.is_dir():
        pytest.skip(f"real DTU scene not present at {SCAN65}")
    return monosdf_copy(tmp_path_factory.mktemp("monosdf") / "scan65", masks=True)


@needs_dtu
def test_a_monosdf_crop_gets_the_whole_frames_cameras_cropped_and_scaled(cropped):
    assert detect_layout(cropped)[0] == "DTU/IDR"
    whole = DTUDataParserConfig(data=SCAN65).setup().get_dataparser_outputs("train").cameras
    crop = DTUDataParserConfig(data=cropped).setup().get_dataparser_outputs("train").cameras
    scale = CROP / 300.0  # 400x300 -> its middle 300x300 -> 384x384
    assert int(crop.width[0, 0]) == CROP and int(crop.height[0, 0]) == CROP
    assert torch.allclose(crop.camera_to_worlds, whole.camera_to_worlds)
    assert torch.allclose(crop.fx, whole.fx * scale, rtol=1e-5) and torch.allclose(crop.fy, whole.fy * scale, rtol=1e-5)
    assert torch.allclose(crop.cx, (whole.cx - 50.0) * scale, atol=1e-3)
    assert torch.allclose(crop.cy, whole.cy * scale, atol=1e-3)
    # The same world ray through corresponding pixels (a pixel of the crop and its place in the whole image).
    crop_rays = crop.generate_rays(camera_indices=0, coords=torch.tensor([[100.0, 200.0]]))
    whole_rays = whole.generate_rays(camera_indices=0, coords=torch.tensor([[100.0 / scale, 200.0 / scale + 50.0]]))
    assert torch.allclose(crop_rays.directions, whole_rays.directions, atol=1e-5)


@needs_dtu
def test_a_monosdf_crops_sparse_points_are_the_uncropped_scenes(cropped):
    def points(folder):
        outputs = DTUDataParserConfig(data=folder).setup().get_dataparser_outputs("train")
        images = [np.asarray(Image.open(p).convert("RGB")) for p in outputs.image_filenames]
        c = outputs.cameras
        intrinsics = torch.cat([c.fx, c.fy, c.cx, c.cy], dim=1)
        sparse = triangulate_training_views(images, c.camera_to_worlds, intrinsics, TriangulationOptions(), progress=False)
        return sparse.points.float()

    whole, crop = points(SCAN65), points(cropped)
    assert whole.shape[0] >= 10 and crop.shape[0] >= 10
    # Each point of the crop lies where a point of the whole images does (the unit sphere's frame: 1 = the radius).
    nearest = torch.cdist(crop, whole).min(dim=1).values
    assert float(nearest.median()) < 0.01


@needs_dtu
def test_a_dtu_folder_without_masks_names_the_option_that_scores_whole_images(tmp_path):
    folder = monosdf_copy(tmp_path / "scan65", masks=False)
    parser = DTUDataParserConfig(data=folder).setup()
    assert parser.get_dataparser_outputs("train").cameras.shape[0] == 2  # training needs no mask
    with pytest.raises(DataError, match="--masked-eval False"):
        parser.get_dataparser_outputs("test")
    test = DTUDataParserConfig(data=folder, masked_eval=False).setup().get_dataparser_outputs("test")
    assert len(test.image_filenames) == 40 and "eval_mask_filenames" not in test.metadata


def intrinsics(cx: float, cy: float, focal: float = 1000.0) -> np.ndarray:
    return np.array([[focal, 0.0, cx], [0.0, focal, cy], [0.0, 0.0, 1.0]])


def test_a_whole_frame_is_scaled_by_its_integer_factor_and_dtus_frame_by_its_own_size():
    assert fit_to_images(intrinsics(640.0, 480.0), 320, 240, None, Path("c.npz")).scale == 0.25
    # DTU's principal point (823, 619) names its 1600x1200 frame, also at a size that is no integer factor.
    fit = fit_to_images(intrinsics(823.2, 619.1), 384, 288, None, Path("c.npz"))
    assert fit.scale == pytest.approx(384 / 1600) and fit.crop_x == 0.0


def test_cameras_that_fit_no_reading_of_their_images_stop_with_one_line():
    # A 4:3 principal point on square images of an unknown frame: which crop, unknown.
    with pytest.raises(DataError, match=r"c\.npz: .*\(640\.0, 480\.0\).*intrinsics-width"):
        fit_to_images(intrinsics(640.0, 480.0), 300, 300, None, Path("c.npz"))
    # A principal point far from the centre of the images it lands in.
    with pytest.raises(DataError, match=r"c\.npz: the cameras do not fit the 400x300 images.*middle third"):
        fit_to_images(intrinsics(823.2, 619.1), 400, 300, 4000, Path("c.npz"))
    # The frame's width given: a crop of a frame no table knows.
    fit = fit_to_images(intrinsics(960.0, 540.0), 540, 540, 1920, Path("c.npz"))
    assert fit.crop_x == pytest.approx(420.0) and fit.scale == pytest.approx(0.5)


def neus_copy(folder: Path, poses_bounds: bool, masks: bool = True) -> Path:
    """scan65 as NeuS's forks distribute DTU: ``images/000000.png``, masks ``mask/000.png``, ``cameras_sphere.npz``;
    with ``poses_bounds`` an LLFF file beside them (any N x 17 rows: the forks write one for LLFF loaders)."""
    folder.mkdir(parents=True)
    shutil.copy(SCAN65 / "cameras_sphere.npz", folder / "cameras_sphere.npz")
    shutil.copytree(SCAN65 / "image", folder / "images")
    if masks:
        (folder / "mask").mkdir()
        for path in sorted((SCAN65 / "mask").glob("*.png")):
            shutil.copy(path, folder / "mask" / f"{int(path.stem):03d}.png")
    if poses_bounds:
        rows = np.zeros((49, 17))
        rows[:, :15] = np.concatenate([np.eye(3), np.zeros((3, 1)), [[300.0], [400.0], [350.0]]], 1).reshape(-1)
        rows[:, 15:] = [1.0, 10.0]
        np.save(folder / "poses_bounds.npy", rows)
    return folder


@needs_dtu
def test_neus_layout_with_images_and_three_digit_masks_reads_as_the_published_scene(tmp_path, capsys):
    folder = neus_copy(tmp_path / "dtu_scan65", poses_bounds=True)
    assert detect_layout(folder)[0] == "DTU/IDR"  # cameras npz + masks: DTU, though poses_bounds.npy sits beside
    auto = AutoDataParserConfig(data=folder).setup()
    train = auto.get_dataparser_outputs("train")
    assert "its cameras npz and mask/ make it DTU" in capsys.readouterr().out
    published = DTUDataParserConfig(data=SCAN65).setup()
    assert torch.equal(train.cameras.camera_to_worlds, published.get_dataparser_outputs("train").cameras.camera_to_worlds)
    test, published_test = auto.get_dataparser_outputs("test"), published.get_dataparser_outputs("test")
    assert [p.name for p in test.image_filenames] == [p.name for p in published_test.image_filenames]
    # The pixelNeRF protocol's masks, each the one of its own image (000000.png pairs with 000.png).
    masks = test.metadata["eval_mask_filenames"]
    assert [int(m.stem) for m in masks] == [int(p.stem) for p in test.image_filenames]
    assert len(test.metadata["test_subsets"]["regnerf25"]) == 25


@needs_dtu
def test_cameras_npz_and_poses_bounds_without_masks_stay_llff(tmp_path):
    folder = neus_copy(tmp_path / "x", poses_bounds=True, masks=False)
    assert detect_layout(folder)[0] == "LLFF"


def test_a_dtu_folder_with_neither_image_folder_names_both(tmp_path):
    np.savez(tmp_path / "cameras.npz", world_mat_0=np.eye(4))
    with pytest.raises(DataError, match=r"neither image/ nor images/ nor MonoSDF"):
        DTUDataParserConfig(data=tmp_path).setup().get_dataparser_outputs("train")


def test_a_colmap_project_with_a_stray_cameras_npz_stays_colmap(tmp_path):
    from tests import layout_fixtures as fx

    fx.write_colmap(tmp_path / "c")
    np.savez(tmp_path / "c" / "cameras.npz", world_mat_0=np.eye(4))
    assert detect_layout(tmp_path / "c")[0] == "COLMAP"
