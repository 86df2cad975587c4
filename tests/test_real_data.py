"""The paper's splits on the real scenes in ../shared/data (skipped where that folder is absent)."""

from pathlib import Path

import pytest
import torch

from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
from frugalnerf_ns.data.dataparsers.dtu import DTUDataParserConfig
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
FERN, SCAN65 = DATA / "llff" / "fern", DATA / "dtu" / "scan65"
needs_fern = pytest.mark.skipif(not FERN.is_dir(), reason=f"real LLFF scene not present at {FERN}")
needs_dtu = pytest.mark.skipif(not SCAN65.is_dir(), reason=f"real DTU scene not present at {SCAN65}")


@needs_fern
def test_fern_paper_split():
    parser = LLFFDataParserConfig(data=FERN).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert [p.name for p in train.image_filenames] == ["image006.png", "image013.png"]
    assert [p.name for p in test.image_filenames] == ["image000.png", "image008.png", "image016.png"]
    # 1/8 resolution: 504x378, focal scaled from the 4032-wide capture.
    assert int(train.cameras.width[0, 0]) == 504 and int(train.cameras.height[0, 0]) == 378
    assert 380 < float(train.cameras.fx[0, 0]) < 430
    assert detect_layout(FERN)[0] == "LLFF"


@needs_dtu
def test_dtu_paper_split_and_masks():
    parser = DTUDataParserConfig(data=SCAN65).setup()
    train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
    assert [p.name for p in train.image_filenames] == ["000022.png", "000025.png"]
    excluded = {0, 8, 13, 22, 25, 28, 40, 44, 48}
    assert [p.name for p in test.image_filenames] == [f"{i:06d}.png" for i in range(49) if i not in excluded]
    assert len(test.metadata["eval_mask_filenames"]) == 40
    # Intrinsics refer to 1600x1200; the images are 400x300.
    assert 700 < float(train.cameras.fx[0, 0]) < 750 and 180 < float(train.cameras.cx[0, 0]) < 230
    # Cameras look at the unit sphere around the object.
    c2w = train.cameras.camera_to_worlds
    to_centre = torch.nn.functional.normalize(-c2w[:, :3, 3], dim=-1)
    assert (torch.einsum("ni,ni->n", -c2w[:, :3, 2], to_centre) > 0.95).all()
    assert detect_layout(SCAN65)[0] == "DTU/IDR"


@needs_fern
def test_fern_four_views_sampled_uniformly_from_non_test_frames():
    outputs = AutoDataParserConfig(data=FERN, num_train_views=4).setup().get_dataparser_outputs("train")
    names = [p.name for p in outputs.image_filenames]
    assert len(names) == 4 and not {"image000.png", "image008.png", "image016.png"} & set(names)


FLOWER = DATA / "llff" / "flower"


@pytest.mark.skipif(not FLOWER.is_dir(), reason=f"real LLFF scene not present at {FLOWER}")
def test_flower_paper_split_at_both_resolutions():
    for factor, width, height in ((8, 504, 378), (4, 1008, 756)):  # CPU and the paper's (GPU) resolution
        parser = LLFFDataParserConfig(data=FLOWER, downscale_factor=factor).setup()
        train, test = parser.get_dataparser_outputs("train"), parser.get_dataparser_outputs("test")
        assert [p.name for p in train.image_filenames] == ["image011.png", "image022.png"]
        assert [p.name for p in test.image_filenames] == [f"image{i:03d}.png" for i in (0, 8, 16, 24, 32)]
        assert (int(train.cameras.width[0, 0]), int(train.cameras.height[0, 0])) == (width, height)
        assert f"images_{factor}" in str(train.image_filenames[0])


@needs_dtu
def test_dtu_regnerf_test_list_is_marked_within_the_pixelnerf_list():
    test = DTUDataParserConfig(data=SCAN65).setup().get_dataparser_outputs("test")
    names = [int(p.stem) for p in test.image_filenames]
    regnerf = sorted(names[n] for n in test.metadata["test_subsets"]["regnerf25"])
    assert regnerf == [1, 2, 9, 10, 11, 12, 14, 15, 23, 24, 26, 27, 29, 30, 31, 32, 33, 34, 35, 41, 42, 43, 45, 46, 47]
