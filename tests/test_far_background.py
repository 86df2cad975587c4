"""The learned far background of scenes whose box holds only their near part (pure torch, then in the model), as the
last layer alone (``outer_space_resolution`` 0); tests/test_outer_space.py has the space beyond the box in front of it."""

import math

import torch
from nerfstudio.cameras.rays import RayBundle

from frugalnerf_ns.field.far_background import FarBackground, direction_to_latlong, shell_distance
from frugalnerf_ns.geometry.scene_analysis import far_shell
from frugalnerf_ns.batch import TrainBatch
from tests.helpers import tiny_model


def test_directions_map_to_the_latlong_square_with_the_seam_behind_the_cameras():
    directions = torch.tensor([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, -1.0, 0.0],
                               [0.0, 0.0, 2.0]])
    lon, lat = direction_to_latlong(directions).unbind(-1)
    assert torch.allclose(lon[:3], torch.tensor([0.0, 0.5, -0.5]), atol=1e-6)
    assert torch.allclose(lat, torch.tensor([0.0, 0.0, 0.0, -1.0, 1.0, 0.0]), atol=1e-6)  # up is row 0
    assert math.isclose(abs(float(lon[5])), 1.0, abs_tol=1e-6)  # +z (behind): the seam, |longitude| = 1


def test_a_fresh_map_is_grey_and_a_direction_learns_its_colour_without_changing_the_opposite_one():
    background = FarBackground((8, 16))
    ahead, behind = torch.tensor([[0.0, 0.0, -1.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    origin = torch.zeros(1, 3)
    assert torch.allclose(background(torch.zeros(2, 3), torch.cat([ahead, behind])), torch.full((2, 3), 0.5))
    optimizer = torch.optim.Adam(background.parameters(), lr=0.1)
    red = torch.tensor([[1.0, 0.0, 0.0]])
    for _ in range(200):
        optimizer.zero_grad()
        ((background(origin, ahead) - red) ** 2).sum().backward()
        optimizer.step()
    assert (background(origin, ahead) - red).abs().max() < 0.05
    assert torch.allclose(background(origin, behind), torch.full((1, 3), 0.5))
    # Infinitely far away: a ray from elsewhere in the same direction sees the same colour (no parallax).
    assert torch.equal(background(torch.tensor([[3.0, -2.0, 1.0]]), ahead), background(origin, ahead))
    # Bilinear: one direction reads (and so trains) at most 2 x 2 texels.
    assert int((background.texture.detach() != 0).any(dim=1).sum()) <= 4


def test_no_rays_give_no_colours():
    assert FarBackground()(torch.zeros(0, 3), torch.zeros(0, 3)).shape == (0, 3)
    assert FarBackground(radius=2.0)(torch.zeros(0, 3), torch.zeros(0, 3)).shape == (0, 3)


def test_a_ray_leaves_the_sphere_at_its_far_root():
    centre = torch.tensor([1.0, 0.0, 0.0])
    origins = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [2.0, 0.0, 0.0], [1.0, 0.5, 0.0], [9.0, 9.0, 0.0]])
    directions = torch.nn.functional.normalize(torch.tensor(
        [[0.0, 0.0, -1.0], [1.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), dim=-1)
    distance = shell_distance(origins, directions, centre, 3.0)
    # From the centre: the radius; from an off-centre origin the exit point lies on the sphere.
    assert torch.allclose(distance[:2], torch.tensor([3.0, 3.0]))
    assert torch.allclose(distance[2], torch.tensor(4.0))  # 1 off-centre, looking back through the centre
    exits = origins[:4] + directions[:4] * distance[:4, None]
    assert torch.allclose((exits - centre).norm(dim=-1), torch.full((4,), 3.0))
    assert float(distance[4]) == 0.0  # outside the sphere, looking away from it: never negative


def test_on_a_sphere_the_map_has_parallax():
    """Two cameras looking the same way at a sphere of radius 2 see different texels; seen infinitely far away
    they would see the same one. Where both look at the same point of the sphere, they see the same colour."""
    background = FarBackground((16, 32), torch.zeros(3), 2.0)
    with torch.no_grad():
        background.texture.copy_(torch.randn(1, 3, 16, 32, generator=torch.Generator().manual_seed(0)))
    left, right = torch.tensor([[-1.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    ahead = torch.tensor([[0.0, 0.0, -1.0]])
    assert (background(left, ahead) - background(right, ahead)).abs().max() > 0.01
    target = torch.tensor([[0.0, 0.0, -2.0]])  # on the sphere, straight ahead of the centre
    to_target = lambda origin: torch.nn.functional.normalize(target - origin, dim=-1)  # noqa: E731
    assert torch.allclose(background(left, to_target(left)), background(right, to_target(right)), atol=1e-5)
    assert torch.allclose(background(left, to_target(left)), background(torch.zeros(1, 3), ahead), atol=1e-5)


def test_the_sphere_is_the_median_distance_of_the_points_beyond_the_box_and_never_inside_it():
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    inside = torch.rand(50, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1
    beyond = torch.tensor([[4.0, 0.0, 0.0], [0.0, -5.0, 0.0], [0.0, 0.0, 6.0], [7.0, 0.0, 0.0], [0.0, 8.0, 0.0]])
    centre, radius = far_shell(torch.cat([inside, beyond]), box)
    assert torch.equal(centre, torch.zeros(3)) and radius == 6.0
    assert far_shell(torch.cat([inside, beyond[:4]]), box) is None  # 4 points beyond: too few to say
    near = torch.tensor([[1.1, 0.0, 0.0]] * 5)  # just outside the box: the sphere still holds the whole box
    assert far_shell(near + 2.0, box + 2.0)[1] == far_shell(near, box)[1] == math.sqrt(3.0)
    assert torch.equal(far_shell(near + 2.0, box + 2.0)[0], torch.full((3,), 2.0))


def bundle(origins, directions):
    n = origins.shape[0]
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(n, 1),
                     camera_indices=torch.zeros(n, 1).long())


def test_the_model_has_a_far_background_only_where_the_dataparser_asks_and_renders_it_behind_the_field():
    assert tiny_model().far_background is None
    assert tiny_model({"far_background": True}, far_background=False).far_background is None
    plain, model = tiny_model(), tiny_model({"far_background": True}, outer_space_resolution=0)  # the same seeded field
    assert model.far_background is not None
    assert any(p is model.far_background.texture for p in model.get_param_groups()["encodings"])
    with torch.no_grad():
        model.far_background.texture[:, 0] = 3.0  # red everywhere
        model.far_background.texture[:, 1:] = -3.0
    gen = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(32, 3, generator=gen), dim=-1)
    rays = bundle(torch.zeros(32, 3), directions)
    plain.eval()
    model.eval()
    with torch.no_grad():
        on_white, on_map = plain.get_outputs(rays), model.get_outputs(rays)
        colours = model.far_background(torch.zeros(32, 3), directions)
    acc = on_map["accumulation"]
    assert torch.equal(acc, on_white["accumulation"]) and float((1 - acc).min()) > 0.1
    # Volume rendering's last term: what the field lets through shows the map's colour instead of white.
    assert torch.allclose(on_map["rgb"] - on_white["rgb"], (1 - acc) * (colours - 1.0), atol=1e-5)
    assert float(colours[:, 0].min()) > 0.9 and float(colours[:, 1:].max()) < 0.1


def test_training_sends_gradient_to_the_far_background_and_a_checkpoint_restores_it():
    model = tiny_model({"far_background": True}, outer_space_resolution=0)
    model.train()
    gen = torch.Generator().manual_seed(1)
    n = 64
    directions = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen), dim=-1)
    outputs = model.get_outputs(bundle(torch.zeros(n, 3), directions))
    batch = TrainBatch(image=torch.rand(n, 3, generator=gen), indices=torch.zeros(n, 3, dtype=torch.long), patch_size=1,
                       nearest_view=torch.full((n,), -1))
    loss = sum(model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch)).values())
    loss.backward()
    assert model.far_background.texture.grad is not None and model.far_background.texture.grad.abs().sum() > 0
    with torch.no_grad():
        model.far_background.texture.add_(torch.randn_like(model.far_background.texture))
    fresh = tiny_model({"far_background": True}, outer_space_resolution=0)
    fresh.load_state_dict(model.state_dict())
    assert torch.equal(fresh.far_background.texture, model.far_background.texture)
    # The sphere too: eval tools build the model without the datamanager's points, then load the checkpoint.
    shell = tiny_model({"far_background": True, "frugalnerf_scene": {"far_shell": ([0.5, 0.0, -1.0], 4.0)}}, outer_space_resolution=0)
    fresh.load_state_dict(shell.state_dict())
    assert fresh.far_background.has_shell and float(fresh.far_background.radius) == 4.0
    assert fresh.far_background.centre.tolist() == [0.5, 0.0, -1.0]


def test_an_old_checkpoint_without_the_sphere_loads_with_the_background_infinitely_far():
    old = {"texture": torch.ones(1, 3, 8, 16)}
    background = FarBackground((8, 16), torch.ones(3), 5.0)
    background.load_state_dict(old)
    assert not background.has_shell and torch.equal(background.texture, old["texture"])
    assert background.distance(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, -1.0]])) is None


def accumulation_before_and_after_sparse_depth_steps(metadata, steps=30):
    """Mean accumulation of 4 sparse rays (from the box's centre, target depth 3) in a dense box of side 2,
    before and after ``steps`` Adam steps on L_sd alone."""
    model = tiny_model(metadata, density_l1_weight=0.0, distortion_weight=0.0, outer_space_resolution=0)
    with torch.no_grad():  # a field that starts dense: every ray through the box is opaque
        for parameter in [*model.field.density_grid.planes, *model.field.density_grid.lines]:
            parameter.fill_(0.2)
    model.train()
    n_train, gen = 9, torch.Generator().manual_seed(2)
    directions = torch.nn.functional.normalize(torch.randn(n_train + 4, 3, generator=gen), dim=-1)
    rays = bundle(torch.zeros(n_train + 4, 3), directions)
    batch = TrainBatch(image=torch.rand(n_train, 3, generator=gen), indices=torch.zeros(n_train, 3, dtype=torch.long),
                       patch_size=1, nearest_view=torch.full((n_train,), -1), sparse_depth=torch.full((4,), 3.0))
    with torch.no_grad():
        first = model.get_outputs(rays)
    optimizer = torch.optim.Adam(model.field.parameters(), lr=0.05)
    for _ in range(steps):
        optimizer.zero_grad()
        outputs = model.get_outputs(rays)
        model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))["sparse_depth"].backward()
        optimizer.step()
    with torch.no_grad():
        after = model.get_outputs(rays)["accumulation"][batch.sparse].mean()
    return model, first, float(first["accumulation"][batch.sparse].mean()), float(after)


def test_a_sparse_point_beyond_the_box_empties_its_ray_through_the_box():
    """L_sd with the sphere behind the field: a point triangulated beyond the box is reached only by a ray that
    crosses the box empty, so its loss lowers the ray's accumulation; without the sphere the field's depth, which
    ends in the box, is all L_sd sees, and the ray stays opaque."""
    shell = {"far_background": True, "frugalnerf_scene": {"far_shell": ([0.0, 0.0, 0.0], 3.0)}}
    model, first, start, after = accumulation_before_and_after_sparse_depth_steps(shell)
    assert model.far_background.has_shell and float(model.far_background.radius) == 3.0
    assert torch.allclose(first["step"].background_depth, torch.full((13,), 3.0))  # from the centre: the radius
    assert start > 0.99 and after < 0.5
    model, first, start, after = accumulation_before_and_after_sparse_depth_steps({"far_background": True})
    assert not model.far_background.has_shell and first["step"].background_depth is None
    assert start > 0.99 and after > 0.9


def test_the_points_beyond_the_box_place_the_sphere_and_are_kept_only_when_wanted(tmp_path):
    """``training_view_points`` through the real points cache: with a far background the points beyond the box
    set the sphere (their median distance) and stay for L_sd; without, a metric box keeps only its own."""
    import numpy as np
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
    from nerfstudio.data.scene_box import SceneBox

    from frugalnerf_ns.data.sparse_points import SparseDepth, TriangulationOptions
    from frugalnerf_ns.data.training_points import cache_key, save_sparse_depth
    from frugalnerf_ns.data.training_views import training_view_points

    c2w = torch.eye(4)[None, :3].repeat(2, 1, 1)
    c2w[1, 0, 3] = 0.5
    cameras = Cameras(camera_to_worlds=c2w, fx=20.0, fy=20.0, cx=8.0, cy=6.0, width=16, height=12)
    rgb = torch.rand(2, 12, 16, 3, generator=torch.Generator().manual_seed(0))
    intrinsics = torch.tensor([[20.0, 20.0, 8.0, 6.0]] * 2)
    box = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    outputs = DataparserOutputs(image_filenames=[tmp_path / "a.png", tmp_path / "b.png"], cameras=cameras,
                                scene_box=SceneBox(aabb=box), metadata={"far_background": True})
    points = torch.tensor([[0.0, 0.0, -0.5], [0.2, 0.1, -0.8], [0.0, 0.0, -4.0], [1.0, 0.0, -5.0], [0.0, 1.0, -6.0],
                           [0.0, -1.0, -7.0], [0.5, 0.5, -8.0]], dtype=torch.float64)
    count = len(points)
    sparse = SparseDepth(points, torch.zeros(count, dtype=torch.long), torch.arange(count),
                         torch.full((count, 2), 4.0, dtype=torch.float64), points.norm(dim=-1))
    options = TriangulationOptions()
    images = [np.round(image.numpy() * 255.0).astype(np.uint8) for image in rgb]
    cache = tmp_path / "sparse.npz"
    save_sparse_depth(cache, sparse, cache_key(images, c2w.double(), intrinsics.double(), options))
    kept, shell, beyond = training_view_points(outputs, cameras, rgb, intrinsics, options, 2, cache, "cpu", True)
    assert kept.num_points == count and shell is not None
    assert shell[0] == [0.0, 0.0, 0.0] and abs(shell[1] - float(points[2:].norm(dim=-1).median())) < 1e-6
    # The count the warp regime reads: 5 of the 7 points lie beyond the box.
    assert beyond == (5, 7)
    inside, none, no_count = training_view_points(outputs, cameras, rgb, intrinsics, options, 2, cache, "cpu", False)
    assert none is None and inside.num_points == 2 and no_count is None


def test_a_model_without_a_far_background_turns_the_datamanagers_sphere_off(procedural_scene, tmp_path):
    """--pipeline.model.far-background False: the datamanager must not keep points beyond the box either."""
    from frugalnerf_ns.data.dataparsers.nerfstudio_format import FewShotNerfstudioDataParserConfig
    from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
    from frugalnerf_ns.run.pipeline import FrugalPipelineConfig
    from tests.helpers import TINY_MODEL

    def pipeline(far_background):
        datamanager = FrugalDataManagerConfig(
            dataparser=FewShotNerfstudioDataParserConfig(data=procedural_scene), train_num_rays_per_batch=100,
            num_novel_rays_per_batch=40, patch_size=3, sparse_cache_dir=tmp_path, sparse_depth=False,
        )
        model = FrugalNeRFModelConfig(**TINY_MODEL, far_background=far_background)
        return FrugalPipelineConfig(datamanager=datamanager, model=model).setup(device="cpu", test_mode="val")

    assert pipeline(True).datamanager.config.far_background_shell
    assert not pipeline(False).datamanager.config.far_background_shell


def test_a_checkpoint_without_the_far_background_stops_loading_with_one_line(tmp_path):
    """A run saved before its layout got the box (trained in NDC, no far background in its checkpoint) must not
    load silently into today's model: nerfstudio retries a failed strict load without strictness, which would
    render the NDC grid in the metric box. Through the evaluation tools' loader (one line, no traceback), on photos 21 degrees either
    side of their mean (a box with a far background) and a real checkpoint file."""
    import types

    import pytest

    from frugalnerf_ns.data.dataparsers.photos import PhotosDataParserConfig
    from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
    from frugalnerf_ns.errors import UserError
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
    from nerfstudio.utils import eval_utils

    from frugalnerf_ns.run.checkpoints import checkpoint_file_name
    from frugalnerf_ns.run.pipeline import FrugalPipelineConfig
    from tests.helpers import TINY_MODEL
    from tests.photo_scene import camera, write_photos

    # The model alone: a checkpoint of a model without a far background.
    with pytest.raises(UserError, match="has no far background.*set `ndc: true`"):
        tiny_model({"far_background": True}, outer_space_resolution=0).load_state_dict(tiny_model().state_dict())

    wide = [camera((x, 0.1 * i, 0.0), target=(0.0, 0.0, -1.8)) for i, x in enumerate((-0.7, 0.0, 0.7))]
    data = write_photos(tmp_path / "wide", wide)
    datamanager = FrugalDataManagerConfig(
        dataparser=PhotosDataParserConfig(data=data), train_num_rays_per_batch=100, num_novel_rays_per_batch=40,
        patch_size=3, sparse_cache_dir=tmp_path,
    )
    pipeline = FrugalPipelineConfig(datamanager=datamanager, model=FrugalNeRFModelConfig(**TINY_MODEL)).setup(
        device="cpu", test_mode="val"
    )
    assert pipeline.model.far_background is not None
    state = pipeline.state_dict()
    folder = tmp_path / "nerfstudio_models"
    folder.mkdir()
    torch.save({"step": 7, "pipeline": state}, folder / checkpoint_file_name(7))
    config = types.SimpleNamespace(load_dir=folder, load_step=None)
    # ns-eval's, ns-render's and the viewer's loader (FrugalPipeline installs the project's in its place).
    assert eval_utils.eval_load_checkpoint(config, pipeline)[1] == 7  # today's checkpoint loads
    old = {k: v for k, v in state.items() if ".far_background." not in k}
    assert len(old) < len(state)
    torch.save({"step": 8, "pipeline": old}, folder / checkpoint_file_name(8))
    with pytest.raises(SystemExit, match=r"^frugalnerf: error: this run's checkpoint has no far background"):
        eval_utils.eval_load_checkpoint(config, pipeline)
