"""The learned far background of scenes whose box holds only their near part (pure torch, then in the model)."""

import math

import torch
from nerfstudio.cameras.rays import RayBundle

from frugalnerf_ns.field.far_background import FarBackground, direction_to_latlong
from frugalnerf_ns.model.batch import TrainBatch
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
    assert torch.allclose(background(torch.cat([ahead, behind])), torch.full((2, 3), 0.5))
    optimizer = torch.optim.Adam(background.parameters(), lr=0.1)
    red = torch.tensor([[1.0, 0.0, 0.0]])
    for _ in range(200):
        optimizer.zero_grad()
        ((background(ahead) - red) ** 2).sum().backward()
        optimizer.step()
    assert (background(ahead) - red).abs().max() < 0.05
    assert torch.allclose(background(behind), torch.full((1, 3), 0.5))
    # Bilinear: one direction reads (and so trains) at most 2 x 2 texels.
    assert int((background.texture.detach() != 0).any(dim=1).sum()) <= 4


def test_no_rays_give_no_colours():
    assert FarBackground()(torch.zeros(0, 3)).shape == (0, 3)


def bundle(origins, directions):
    n = origins.shape[0]
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(n, 1),
                     camera_indices=torch.zeros(n, 1).long())


def test_the_model_has_a_far_background_only_where_the_dataparser_asks_and_renders_it_behind_the_field():
    assert tiny_model().far_background is None
    assert tiny_model({"far_background": True}, far_background=False).far_background is None
    plain, model = tiny_model(), tiny_model({"far_background": True})  # the same seeded field
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
        colours = model.far_background(directions)
    acc = on_map["accumulation"]
    assert torch.equal(acc, on_white["accumulation"]) and float((1 - acc).min()) > 0.1
    # Volume rendering's last term: what the field lets through shows the map's colour instead of white.
    assert torch.allclose(on_map["rgb"] - on_white["rgb"], (1 - acc) * (colours - 1.0), atol=1e-5)
    assert float(colours[:, 0].min()) > 0.9 and float(colours[:, 1:].max()) < 0.1


def test_training_sends_gradient_to_the_far_background_and_a_checkpoint_restores_it():
    model = tiny_model({"far_background": True})
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
    fresh = tiny_model({"far_background": True})
    fresh.load_state_dict(model.state_dict())
    assert torch.equal(fresh.far_background.texture, model.far_background.texture)
