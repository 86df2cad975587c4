"""Real captures in NeRF-synthetic's file names (instant-ngp's and TensoRF's custom data) read as captures: the
file's intrinsics and distortion, a box around the cameras' focus with the space beyond it; a true NeRF-synthetic
scene reads as before. The bird (skipped where ../shared/data is absent) written as instant-ngp writes it is read
against the same frames read as LLFF."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.dataparsers.blender import BlenderDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.procedural_scene import SceneSpec, write_blender_scene
from tests import layout_fixtures as fx

BIRD = Path(__file__).resolve().parents[2] / "shared" / "data" / "captures" / "bird"
needs_bird = pytest.mark.skipif(not BIRD.is_dir(), reason=f"real capture not present at {BIRD}")
TRAIN, TEST = [0, 23, 46], [12, 35]


@pytest.fixture(scope="module")
def bird_ngp(tmp_path_factory):
    if not BIRD.is_dir():
        pytest.skip(f"real capture not present at {BIRD}")
    return fx.llff_capture_as_instant_ngp(BIRD, tmp_path_factory.mktemp("ngp") / "bird", TRAIN, TEST)


def relative_geometry(c2w: torch.Tensor):
    """What a similarity transform of the world keeps: rotations between cameras and ratios of their distances."""
    c2w = c2w.double()
    rotations = c2w[:, :3, :3]
    relative = rotations[0].T @ rotations[1:]
    centres = c2w[:, :3, 3]
    gaps = torch.stack([(centres[i] - centres[j]).norm() for i, j in ((0, 1), (0, 2), (1, 2))])
    return relative, gaps / gaps[0]


@needs_bird
def test_a_capture_written_as_instant_ngp_reads_as_the_same_capture_as_its_llff_files(bird_ngp, capsys):
    assert detect_layout(bird_ngp)[0] == "NeRF-synthetic files (Blender or a capture)"
    parser = AutoDataParserConfig(data=bird_ngp, train_views=(0, 1, 2), test_views=(0, 1)).setup()
    train = parser.get_dataparser_outputs("train")
    line = " ".join(capsys.readouterr().out.split())
    assert "a real capture in NeRF-synthetic's file names" in line and "no alpha" in line and "fl_x" in line
    assert "with the space beyond it" in line
    assert train.metadata.get("far_background") and "ndc" not in train.metadata
    llff = LLFFDataParserConfig(data=BIRD, train_views=tuple(TRAIN), test_views=tuple(TEST)).setup()
    reference = llff.get_dataparser_outputs("train")
    # The same pixels (the LLFF cache's copies and these are both 1/2 of the 544x960 JPEGs), the same cameras up to
    # the frame each reading chooses.
    assert int(train.cameras.width[0, 0]) == 272 and int(train.cameras.height[0, 0]) == 480
    assert torch.allclose(train.cameras.fx, reference.cameras.fx, rtol=1e-4)
    assert torch.allclose(train.cameras.cx, reference.cameras.cx) and torch.allclose(train.cameras.cy, reference.cameras.cy)
    (rot, ratios), (rot_ref, ratios_ref) = relative_geometry(train.cameras.camera_to_worlds), relative_geometry(
        reference.cameras.camera_to_worlds)
    assert torch.allclose(rot, rot_ref, atol=1e-4) and torch.allclose(ratios, ratios_ref, atol=1e-4)
    # Near and far from the points the file's cameras triangulate: the bird's nearest surface ~1/0.75 after scaling,
    # the far bound at least 100x it (the room around the subject).
    near, far = train.metadata["near_far"]
    assert near == pytest.approx(1 / 0.75) and far >= 100 * near
    assert " points, modelled in a box" in line
    test = parser.get_dataparser_outputs("test")
    assert [p.stem for p in test.image_filenames] == [f"{i + 1:03d}" for i in TEST]


@needs_bird
def test_capture_false_reads_a_capture_as_nerf_synthetic(bird_ngp):
    outputs = BlenderDataParserConfig(data=bird_ngp, train_views=(0, 1, 2), capture=False).setup().get_dataparser_outputs("train")
    assert outputs.metadata["near_far"] == (2.0, 6.0) and "far_background" not in outputs.metadata
    assert torch.equal(outputs.scene_box.aabb, torch.tensor([[-1.5] * 3, [1.5] * 3]))


def test_nerf_synthetic_stays_nerf_synthetic_and_says_why(tmp_path, capsys):
    scene = write_blender_scene(tmp_path / "synthetic", SceneSpec(width=32, height=32, focal=35.0), counts=(4, 1, 2))
    outputs = BlenderDataParserConfig(data=scene, train_views=(0, 1)).setup().get_dataparser_outputs("train")
    assert outputs.metadata["near_far"] == (2.0, 6.0) and "far_background" not in outputs.metadata
    assert "NeRF-synthetic: RGBA frames" in " ".join(capsys.readouterr().out.split())


def test_a_synthetic_scene_that_states_intrinsics_or_stands_far_reads_as_a_capture(tmp_path):
    scene = write_blender_scene(tmp_path / "far", SceneSpec(width=32, height=32, focal=35.0), counts=(4, 1, 2))
    for split in ("train", "test"):
        path = scene / f"transforms_{split}.json"
        meta = json.loads(path.read_text())
        for frame in meta["frames"]:
            frame["transform_matrix"] = (np.array(frame["transform_matrix"]) * np.array([1, 1, 1, 4.0])).tolist()
        path.write_text(json.dumps(meta))
    outputs = BlenderDataParserConfig(data=scene, train_views=(0, 1, 2)).setup().get_dataparser_outputs("train")
    assert outputs.metadata.get("far_background") or outputs.metadata.get("ndc")


def test_the_frames_are_undistorted_with_the_files_distortion_and_principal_point(tmp_path):
    """A dot drawn where a distorted camera with an off-centre principal point sees a point lands, in the copy
    training reads, where the pinhole camera the parser returns projects it."""
    width, height, k1 = 160, 120, -0.25
    K = np.array([[120.0, 0.0, 92.0], [0.0, 118.0, 55.0], [0.0, 0.0, 1.0]])
    frames, expected = [], []
    (tmp_path / "images").mkdir()
    for i, (_, w2c) in enumerate(fx.opencv_cameras(3, forward_facing=False)):
        camera = w2c[:3, :3] @ fx.POINT + w2c[:3, 3]
        x, y = camera[0] / camera[2], camera[1] / camera[2]
        r2 = x * x + y * y
        u, v = K[0, 0] * x * (1 + k1 * r2) + K[0, 2], K[1, 1] * y * (1 + k1 * r2) + K[1, 2]
        rows, cols = np.mgrid[0:height, 0:width]
        image = 255.0 * np.exp(-((cols + 0.5 - u) ** 2 + (rows + 0.5 - v) ** 2) / 4.0)
        Image.fromarray(np.repeat(image[..., None], 3, -1).astype(np.uint8)).save(tmp_path / "images" / f"{i}.png")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": fx.opengl_c2w(w2c).tolist()})
        expected.append(fx.project(K, w2c))
    meta = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": width, "h": height, "k1": k1,
            "camera_angle_x": 2 * math.atan(width / (2 * K[0, 0])), "frames": frames}
    for split in ("train", "test"):
        (tmp_path / f"transforms_{split}.json").write_text(json.dumps(meta))
    outputs = BlenderDataParserConfig(data=tmp_path, train_views=(0, 1, 2), test_views=(0,)).setup().get_dataparser_outputs("train")
    assert float(outputs.cameras.cx[0, 0]) == pytest.approx(92.0) and float(outputs.cameras.fy[0, 0]) == pytest.approx(118.0)
    for file, (u, v) in zip(outputs.image_filenames, expected):
        copy = np.asarray(Image.open(file).convert("L"), dtype=np.float64)
        row, col = np.unravel_index(np.argmax(copy), copy.shape)
        assert abs(col + 0.5 - u) <= 1.0 and abs(row + 0.5 - v) <= 1.0, (file, (col, row), (u, v))


def test_a_frame_with_its_own_camera_or_a_fisheye_model_stops_with_one_line(tmp_path):
    fx.write_instant_ngp(tmp_path / "a")
    path = tmp_path / "a" / "transforms_train.json"
    meta = json.loads(path.read_text())
    meta["frames"][2]["fl_x"] = 40.0
    path.write_text(json.dumps(meta))
    with pytest.raises(DataError, match=r"transforms_train.json: frame 2 states its own fl_x"):
        BlenderDataParserConfig(data=tmp_path / "a", train_views=(0, 1)).setup().get_dataparser_outputs("train")
    fx.write_instant_ngp(tmp_path / "b")
    for split in ("train", "test"):
        path = tmp_path / "b" / f"transforms_{split}.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "camera_model": "OPENCV_FISHEYE"}))
    with pytest.raises(DataError, match=r"camera_model 'OPENCV_FISHEYE' is not read"):
        BlenderDataParserConfig(data=tmp_path / "b", train_views=(0, 1)).setup().get_dataparser_outputs("train")
    fx.write_instant_ngp(tmp_path / "c")  # colmap2nerf.py marks a fisheye with is_fisheye and k3 / k4, no model
    for split in ("train", "test"):
        path = tmp_path / "c" / f"transforms_{split}.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), "is_fisheye": True, "k4": 0.01}))
    with pytest.raises(DataError, match=r"a fisheye camera \(is_fisheye / k4\) is not read"):
        BlenderDataParserConfig(data=tmp_path / "c", train_views=(0, 1)).setup().get_dataparser_outputs("train")
