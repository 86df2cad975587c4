"""RealEstate-10K: SLAM poses without scale get their near bound from the training views' points (so the poses' units
do not matter), short clips get splits spread over them, and too few points stop with one line naming the option.
The real clips (skipped where ../shared/data is absent) are 256x256 frames of pixelSplat's RealEstate-10K."""

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from frugalnerf_ns.data.dataparsers.realestate import RealEstateDataParserConfig
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.splits import load_split_table, spread_split
from tests import layout_fixtures as fx

RE10K = Path(__file__).resolve().parents[2] / "shared" / "data" / "re10k"
CLIP = RE10K / "5aca87f95a9412c6"


def parse(data: Path, split: str = "train", **options):
    return RealEstateDataParserConfig(data=data, **options).setup().get_dataparser_outputs(split)


def test_spread_split_tests_only_frames_between_training_frames():
    for frames in (9, 12, 25):
        train, test = spread_split(frames)
        assert sorted(train) == [2, 3, 4]
        for count, views in train.items():
            assert len(set(views)) == count and views[0] == 0 and views[-1] == frames - 1
            assert not set(views) & set(test)
        assert test and all(0 < t < frames - 1 for t in test)
        assert set(test) | {v for views in train.values() for v in views} == set(range(frames))


def test_the_shared_clips_splits_in_splits_yaml_are_the_spread_rule():
    clips = load_split_table()["realestate"]["clips"]
    assert len(clips) == 3
    for name, clip in clips.items():
        frames = clip["train_views"][2][-1] + 1  # the 2-view split holds the first and the last frame
        train, test = spread_split(frames)
        assert clip["train_views"] == train and clip["test"] == test, name
        if (RE10K / name).is_dir():
            assert len(list((RE10K / name / "rgb").iterdir())) == frames


def test_short_clips_spread_their_views_and_long_ones_keep_vip_nerfs_frames(tmp_path):
    fx.write_realestate(tmp_path / "short", count=12)
    train, test = spread_split(12)
    for count in (2, 3, 4):
        outputs = parse(tmp_path / "short", num_train_views=count, near_bound=1.0)
        assert [int(p.stem) for p in outputs.image_filenames] == train[count]
    assert [int(p.stem) for p in parse(tmp_path / "short", "test", near_bound=1.0).image_filenames] == test
    fx.write_realestate(tmp_path / "long", count=40)
    assert [int(p.stem) for p in parse(tmp_path / "long", num_train_views=3, near_bound=1.0).image_filenames] == [10, 20, 30]
    # A longer clip under a shared clip's name is not given that clip's split.
    named = parse(tmp_path / "long", num_train_views=3, near_bound=1.0, scene_name="5aca87f95a9412c6")
    assert [int(p.stem) for p in named.image_filenames] == [10, 20, 30]
    short = parse(tmp_path / "short", num_train_views=3, near_bound=1.0, scene_name="5aca87f95a9412c6")
    assert [int(p.stem) for p in short.image_filenames] == load_split_table()["realestate"]["clips"]["5aca87f95a9412c6"]["train_views"][3]


def test_too_few_points_name_the_option(tmp_path):
    fx.write_realestate(tmp_path / "flat", count=12)  # flat grey frames: nothing to match
    with pytest.raises(DataError, match=r"too few to tell how near the content is: give --near-bound"):
        parse(tmp_path / "flat")
    with pytest.raises(DataError, match="--near-bound must be positive"):
        parse(tmp_path / "flat", near_bound=-1.0)


@pytest.mark.skipif(not CLIP.is_dir(), reason=f"RealEstate-10K clip not present at {CLIP}")
def test_a_real_clip_parses_the_same_whatever_the_poses_units(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    scaled = tmp_path / "scaled"
    scaled.mkdir()
    (scaled / "rgb").symlink_to(CLIP / "rgb")
    shutil.copyfile(CLIP / "CameraIntrinsics.csv", scaled / "CameraIntrinsics.csv")  # not the data's read-only mode
    rows = np.loadtxt(CLIP / "CameraExtrinsics.csv", delimiter=",").reshape(-1, 4, 4)
    rows[:, :3, 3] *= 7.0  # the same clip in other units: SLAM's scale is arbitrary
    np.savetxt(scaled / "CameraExtrinsics.csv", rows.reshape(-1, 16), delimiter=",")
    original, other = parse(CLIP, num_train_views=3), parse(scaled, num_train_views=3)
    said = " ".join(capsys.readouterr().out.split())
    assert said.count("the poses have no scale; the closest content is") == 2 and "--near-bound sets it" in said
    # Equal up to the triangulation's own tolerances (its thresholds are not all scale-free): 0.1% apart here.
    assert torch.allclose(original.cameras.camera_to_worlds, other.cameras.camera_to_worlds, rtol=3e-3, atol=1e-3)
    # The found near bound is where the nearest content is: with it given, the cameras are the same.
    near = float(said.split("the closest content is ")[1].split(" units")[0])
    given = parse(CLIP, num_train_views=3, near_bound=near)
    assert torch.allclose(given.cameras.camera_to_worlds, original.cameras.camera_to_worlds, rtol=2e-3, atol=2e-3)
    # A near bound twice as far shrinks the scene by half about the cameras' average.
    half = parse(CLIP, num_train_views=3, near_bound=2 * near)
    assert torch.allclose(half.cameras.camera_to_worlds[..., 3], original.cameras.camera_to_worlds[..., 3] / 2,
                          rtol=2e-3, atol=2e-3)


@pytest.mark.skipif(not CLIP.is_dir(), reason=f"RealEstate-10K clip not present at {CLIP}")
def test_what_the_training_views_see_lies_beyond_ndcs_near_plane(tmp_path, monkeypatch):
    """The clip walks through a doorway into a room: the wall beside frame 0 must lie beyond z = -1, where NDC's
    rays start, or later views see it drawn in front of them."""
    from frugalnerf_ns.data.scene_bounds import training_points
    from frugalnerf_ns.geometry.camera_conventions import opencv_to_opengl

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    outputs = parse(CLIP, num_train_views=2)
    model = outputs.cameras.camera_to_worlds.double().numpy()
    train = load_split_table()["realestate"]["clips"][CLIP.name]["train_views"][2]
    w2c = np.loadtxt(CLIP / "CameraExtrinsics.csv", delimiter=",").reshape(-1, 4, 4)
    data = opencv_to_opengl(np.linalg.inv(w2c)[:, :3, :4])[train]
    K = np.loadtxt(CLIP / "CameraIntrinsics.csv", delimiter=",").reshape(-1, 3, 3)[train]
    sparse = training_points([CLIP / "rgb" / f"{i:03d}.png" for i in train], data,
                             [(k[0, 0], k[1, 1], k[0, 2], k[1, 2]) for k in K], tmp_path / "points.npz", print)
    # The similarity from the data's frame to the model's, from the two training cameras.
    scale = np.linalg.norm(model[0, :, 3] - model[1, :, 3]) / np.linalg.norm(data[0, :, 3] - data[1, :, 3])
    rotation = model[0, :, :3] @ data[0, :, :3].T
    points = scale * sparse.points.double().numpy() @ rotation.T + (model[0, :, 3] - scale * rotation @ data[0, :, 3])
    assert sparse.num_points > 20
    # Content at the near bound straight ahead of any training camera lies beyond the plane (frame 0 stands 0.87
    # behind the average camera: without the frame moved back its near content would lie behind the plane).
    assert (model[:, 2, 3] - outputs.metadata["near_far"][0] <= -1.0 + 1e-6).all()
    assert (points[:, 2] < -1.0).mean() >= 0.97  # the near bound is the 1st percentile of the depths
