"""The space beyond the scene box as geometry: the contraction (pure torch), the outer grids, and the model with them."""

import math

import pytest
import torch
from nerfstudio.cameras.rays import RayBundle

from frugalnerf_ns.field.outer_space import FAR_BOX_HALVES, OuterSpace
from frugalnerf_ns.geometry.contraction import contract, disparity_bins, interval_distortion, uncontract
from frugalnerf_ns.geometry.raymarch import intersect_aabb
from frugalnerf_ns.batch import TrainBatch
from tests.helpers import tiny_model

BOX = torch.tensor([[-1.0, -2.0, -0.5], [3.0, 2.0, 1.5]])  # centre (1, 0, 0.5), half sizes (2, 2, 1)
CENTRE, HALF = BOX.mean(dim=0), (BOX[1] - BOX[0]) / 2


def test_points_in_and_beyond_the_box_contract_and_come_back_exactly():
    gen = torch.Generator().manual_seed(0)
    inside = BOX[0] + torch.rand(200, 3, generator=gen, dtype=torch.float64) * (BOX[1] - BOX[0])
    directions = torch.nn.functional.normalize(torch.randn(200, 3, generator=gen, dtype=torch.float64), dim=-1)
    beyond = CENTRE + directions * torch.logspace(0.5, 4, 200, dtype=torch.float64)[:, None]  # 3 to 10^4 units
    box64 = (CENTRE.double(), HALF.double())
    assert torch.equal(contract(inside, *box64), (inside - box64[0]) / box64[1])  # the box as it is, in box units
    squeezed = contract(beyond, *box64)
    norms = squeezed.abs().amax(dim=-1)
    assert bool((norms > 1).all() and (norms < 2).all())
    # n box halves away (L-infinity, box units) lands at 2 - 1/n: disparity is linear in the contracted space.
    n = ((beyond - box64[0]) / box64[1]).abs().amax(dim=-1)
    assert torch.allclose(norms, 2 - 1 / n, atol=1e-12)
    for points in (inside, beyond):
        assert torch.allclose(uncontract(contract(points, *box64), *box64), points, rtol=1e-9, atol=1e-9)
    # The contraction is continuous across the box's faces.
    face = torch.tensor([[3.0, 0.3, 0.7]], dtype=torch.float64)
    assert torch.allclose(contract(face + 1e-9, *box64), contract(face - 1e-9, *box64), atol=1e-8)


@pytest.mark.parametrize("jitter", [False, True])
def test_samples_beyond_the_box_are_ordered_in_their_bins_and_equal_in_disparity(jitter):
    t_start, t_end = torch.tensor([0.5, 2.0, 7.0]), torch.tensor([1000.0, 50.0, 14.0])
    edges, t = disparity_bins(t_start, t_end, 16, jitter)
    assert edges.shape == (3, 17) and t.shape == (3, 16)
    assert torch.allclose(edges[:, 0], t_start) and torch.allclose(edges[:, -1], t_end)
    assert bool((edges[:, 1:] > edges[:, :-1]).all() and (t > edges[:, :-1]).all() and (t < edges[:, 1:]).all())
    steps = (1 / edges[:, :-1]) - (1 / edges[:, 1:])
    assert torch.allclose(steps, steps[:, :1].expand_as(steps), rtol=1e-4)


def test_interval_distortion_is_the_double_sum_and_lowest_for_one_surface():
    gen = torch.Generator().manual_seed(4)
    weights = torch.rand(5, 12, generator=gen, dtype=torch.float64) / 12
    mids = (torch.arange(12, dtype=torch.float64) + 0.5) / 12
    brute = (weights[:, :, None] * weights[:, None, :] * (mids[:, None] - mids[None, :]).abs()).sum(dim=(1, 2))
    brute = brute + (weights**2).sum(dim=-1) / (3 * 12)
    assert torch.allclose(interval_distortion(weights), brute, rtol=1e-12)
    surface, fog = torch.zeros(1, 12, dtype=torch.float64), torch.full((1, 12), 0.9 / 12, dtype=torch.float64)
    surface[0, 7] = 0.9  # the same accumulation in one bin or spread over all of them
    assert float(interval_distortion(surface)) < 0.1 * float(interval_distortion(fog))


def outer(resolution=16, samples=24, seed=0):
    torch.manual_seed(seed)
    return OuterSpace(BOX, resolution, 4, 4, samples)


def test_a_ray_is_marched_from_where_it_leaves_the_box_to_far_beyond_and_covers_the_outside():
    space = outer()
    gen = torch.Generator().manual_seed(1)
    origins = BOX[0] + torch.rand(64, 3, generator=gen) * (BOX[1] - BOX[0])
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen), dim=-1)
    t_in, t_out, near = space.segments(origins, directions, 0.0)
    assert torch.equal(t_in, near) and bool((near == 0).all())  # a camera in the box: nothing in front of it
    assert torch.allclose(t_out, intersect_aabb(origins, directions, BOX).t_far)
    exits = origins + directions * t_out[:, None]
    assert torch.allclose(contract(exits, CENTRE, HALF).abs().amax(dim=-1), torch.ones(64), atol=1e-5)
    end = torch.full_like(t_out, FAR_BOX_HALVES * float(HALF.max()))
    edges, _ = disparity_bins(t_out, end, space.num_samples, jitter=False)
    last = contract(origins + directions * edges[:, -1:], CENTRE, HALF).abs().amax(dim=-1)
    assert bool((last > 1.99).all())  # the outside up to 1000 box halves: contracted norm 1 to 1.999
    # Cameras outside the box: the outside in front of it runs from the near plane to the box's entry; a ray
    # that misses the box is split at its closest approach to the centre.
    origins = CENTRE + torch.tensor([[9.0, 0.0, 0.0], [9.0, 0.0, 0.0]])
    directions = torch.nn.functional.normalize(torch.tensor([[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]]), dim=-1)
    t_in, t_out, near = space.segments(origins, directions, 0.5)
    assert torch.allclose(t_in, torch.tensor([7.0, 0.5])) and torch.allclose(t_out, torch.tensor([11.0, 0.5]))


def test_outer_render_is_bounded_and_its_fast_read_equals_the_planes():
    space = outer()
    with torch.no_grad():
        for grid in (space.density_grid, space.appearance_grid):
            for p in [*grid.planes, *grid.lines]:
                p.normal_(0.0, 0.6)
    gen = torch.Generator().manual_seed(2)
    # Half the cameras in the box, half 3 box halves out looking back at it.
    origins = torch.cat([CENTRE + 0.3 * torch.randn(50, 3, generator=gen), CENTRE + torch.tensor([6.0, 0.5, 0.2])
                         + 0.3 * torch.randn(50, 3, generator=gen)])
    directions = torch.randn(100, 3, generator=gen)
    directions[50:, 0] = -directions[50:, 0].abs() - 1.0
    directions = torch.nn.functional.normalize(directions, dim=-1)
    with torch.no_grad():
        fast = space.render(origins, directions, jitter=False)  # baked node table
    slow = space.render(origins, directions, jitter=False)  # the planes, with gradient
    for part_fast, part_slow in zip(fast, slow):
        for a, b in zip(part_fast[:3], part_slow[:3]):  # colour, accumulation, depth (distortion: training only)
            assert torch.allclose(a, b.detach(), rtol=1e-4, atol=1e-4)
    front, behind = slow
    for part in (front, behind):
        acc = part.accumulation.detach()
        assert float(acc.min()) >= 0 and float(acc.max()) <= 1 + 1e-6
    assert float(front.accumulation.detach()[:50].abs().max()) == 0.0  # in the box: nothing in front of it
    assert float(front.accumulation[50:].detach().mean()) > 0.3 and float(behind.accumulation.detach().max()) > 0.5
    t_in, t_out, _ = space.segments(origins, directions, 0.0)
    assert bool((behind.depth.detach() >= t_out - 1e-4).all())  # what the ray sees behind lies beyond the box
    seen = front.accumulation.detach() > 0.01
    # A disparity average of samples before the entry, over the share they stop: nearer than the entry.
    assert bool((front.depth.detach()[seen] * front.accumulation.detach()[seen] <= t_in[seen] + 1e-4).all())
    (front.rgb.sum() + behind.rgb.sum()).backward()
    assert space.density_grid.planes[0].grad.abs().sum() > 0 and space.color_basis.weight.grad.abs().sum() > 0


def bundle(origins, directions):
    n = origins.shape[0]
    return RayBundle(origins=origins, directions=directions, pixel_area=torch.ones(n, 1),
                     camera_indices=torch.zeros(n, 1).long())


def test_only_scenes_with_a_far_background_get_the_outer_space_and_it_renders_behind_the_field():
    assert tiny_model().outer_space is None  # NDC, DTU, Blender, the procedural scene: unchanged
    plain, asked = tiny_model(), tiny_model(outer_space_resolution=64)  # the setting alone adds nothing
    assert list(plain.state_dict()) == list(asked.state_dict())
    probe = bundle(torch.zeros(8, 3), torch.nn.functional.normalize(torch.randn(8, 3), dim=-1))
    plain.eval()
    asked.eval()
    with torch.no_grad():
        assert torch.equal(plain.get_outputs(probe)["rgb"], asked.get_outputs(probe)["rgb"])
    assert tiny_model({"far_background": True}, outer_space_resolution=0).outer_space is None
    model = tiny_model({"far_background": True}, outer_space_resolution=16, outer_space_samples=16)
    assert model.outer_space is not None and model.outer_space.is_active
    groups = model.get_param_groups()
    assert any(p is model.outer_space.density_grid.planes[0] for p in groups["encodings"])
    assert any(p is model.outer_space.color_basis.weight for p in groups["fields"])
    gen = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(32, 3, generator=gen), dim=-1)
    rays = bundle(torch.zeros(32, 3), directions)
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(rays)
        front, beyond = model.outer_space.render(torch.zeros(32, 3), directions, jitter=False)
        far = model.far_background(torch.zeros(32, 3), directions)
        plain = tiny_model({"far_background": True}, outer_space_resolution=0)
        plain.eval()
        box_only = plain.get_outputs(rays)  # the same seeded object field in front of a map only
    acc = out["accumulation"]
    assert torch.equal(acc, box_only["accumulation"]) and float((1 - acc).min()) > 0.1
    background = beyond.rgb + (1 - beyond.accumulation[:, None]) * far
    field_part = box_only["rgb"] - (1 - acc) * plain.far_background(torch.zeros(32, 3), directions)
    assert torch.allclose(out["rgb"], field_part + (1 - acc) * background, atol=1e-5)
    # The depth runs through the box into the room, composited in disparity: acc / d_box + (1 - acc) / d_beyond.
    disparity = acc[:, 0] / box_only["depth"][:, 0] + (1 - acc[:, 0]) / beyond.depth
    assert torch.allclose(out["depth"][:, 0], 1 / disparity, rtol=1e-4)
    assert float(front.accumulation.abs().max()) == 0.0  # cameras in the box: nothing in front of it
    assert float(out["depth"].max()) > 2.0  # beyond the box's half diagonal: not clamped into it


def test_an_old_checkpoint_without_the_outer_space_loads_and_renders_as_it_was_trained():
    before = tiny_model({"far_background": True, "frugalnerf_scene": {"far_shell": ([0.0, 0.0, 0.0], 4.0)}},
                        outer_space_resolution=0)
    with torch.no_grad():
        before.far_background.texture.normal_()
    state = before.state_dict()
    now = tiny_model({"far_background": True}, outer_space_resolution=16)
    now.load_state_dict(state)  # strict: the hook fills the missing outer space
    assert not now.outer_space.is_active and now.far_background.has_shell
    gen = torch.Generator().manual_seed(3)
    rays = bundle(0.2 * torch.randn(40, 3, generator=gen),
                  torch.nn.functional.normalize(torch.randn(40, 3, generator=gen), dim=-1))
    before.eval()
    now.eval()
    with torch.no_grad():
        a, b = before.get_outputs(rays), now.get_outputs(rays)
    for key in ("rgb", "depth", "accumulation"):
        assert torch.equal(a[key], b[key])
    # A checkpoint of today's model keeps its outer space switched on.
    again = tiny_model({"far_background": True}, outer_space_resolution=16)
    fresh = tiny_model({"far_background": True}, outer_space_resolution=16)
    fresh.load_state_dict(again.state_dict())
    assert fresh.outer_space.is_active


WALL_Z, CUBE_HALF = -4.0, 0.25
WALL_TEXTURE = torch.rand(1, 3, 12, 12, generator=torch.Generator().manual_seed(7))
"""Random colours, bilinearly read over x, y in [-8, 8]: not periodic, so only the true depth fits every view (a
sinusoid would fit at every depth whose parallax shifts it by whole periods)."""


def two_depth_scene(origins, directions):
    """Ground truth of a red cube at the origin in front of a textured wall at z = -4: colour and depth."""
    cube = intersect_aabb(origins, directions, torch.tensor([[-CUBE_HALF] * 3, [CUBE_HALF] * 3]))
    t_wall = (WALL_Z - origins[:, 2]) / directions[:, 2]
    xy = (origins + directions * t_wall[:, None])[:, :2] / 8.0
    wall = torch.nn.functional.grid_sample(WALL_TEXTURE, xy[None, None], align_corners=True)[0, :, 0].T
    red = torch.tensor([0.9, 0.1, 0.1]).expand_as(wall)
    rgb = torch.where(cube.hit[:, None], red, wall)
    return rgb, torch.where(cube.hit, cube.t_near, t_wall), cube.hit


def camera_rays(x, width=24, height=18, focal=20.0):
    """A pinhole camera at (x, 0, 0.8) inside the box [-1, 1]^3, looking down -z."""
    j, i = torch.meshgrid(torch.arange(height, dtype=torch.float32), torch.arange(width, dtype=torch.float32), indexing="ij")
    d = torch.stack([(i + 0.5 - width / 2) / focal, -(j + 0.5 - height / 2) / focal, -torch.ones_like(i)], -1)
    d = torch.nn.functional.normalize(d.reshape(-1, 3), dim=-1)
    return torch.tensor([x, 0.0, 0.8]).expand_as(d).contiguous(), d


def test_a_box_in_front_of_a_wall_trained_from_three_views_puts_the_wall_beyond_the_box():
    """The wall lies 4.8 units from the cameras, beyond the box (half side 1): the object's field holds the cube,
    and the wall's rays end beyond the box, in the outer space (the colour map alone had no depth: its rays ended
    on the box's faces). Trained as the pipeline trains (colour, L_sd on 24 points triangulated on the wall, the
    outer distortion), one scale of a 16^3 grid. What it does not show: the wall at its true depth. In this toy it
    ends at about half of it (a fog between the box and the wall fits three views 0.5 apart as well)."""
    model = tiny_model({"far_background": True}, outer_space_resolution=32, outer_space_samples=24,
                       distortion_weight=0.0, density_l1_weight=0.0, appearance_tv_weight=0.0, density_tv_weight=0.0,
                       num_lower_scales=0)
    views = [camera_rays(x) for x in (-0.5, 0.0, 0.5)]
    origins, directions = torch.cat([o for o, _ in views]), torch.cat([d for _, d in views])
    target, true_depth, on_cube = two_depth_scene(origins, directions)
    wall = torch.nonzero(~on_cube)[:, 0]
    sparse = wall[torch.randperm(len(wall), generator=torch.Generator().manual_seed(5))[:24]]
    rays = bundle(torch.cat([origins, origins[sparse]]), torch.cat([directions, directions[sparse]]))
    n = len(origins)
    batch = TrainBatch(image=target, indices=torch.zeros(n, 3, dtype=torch.long), patch_size=1,
                       nearest_view=torch.full((n,), -1), sparse_depth=true_depth[sparse])
    groups = model.get_param_groups()
    optimizer = torch.optim.Adam([{"params": groups["encodings"], "lr": 0.05}, {"params": groups["fields"], "lr": 5e-3}])
    model.train()
    torch.manual_seed(0)
    for _ in range(150):
        optimizer.zero_grad()
        outputs = model.get_outputs(rays)
        losses = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
        assert {"rgb_loss", "sparse_depth", "outer_distortion"} <= set(losses)
        sum(losses.values()).backward()
        optimizer.step()
    model.eval()
    with torch.no_grad():
        out = model.get_outputs(bundle(origins, directions))
    psnr = -10 * math.log10(float(((out["rgb"] - target) ** 2).mean()))
    assert psnr > 25.0
    depth = out["depth"][:, 0]
    box_exit = intersect_aabb(origins, directions, torch.tensor([[-1.0] * 3, [1.0] * 3])).t_far
    wall_depth = depth[~on_cube]
    assert float((wall_depth / box_exit[~on_cube]).median()) > 1.1  # beyond the box, not on its faces
    assert float((wall_depth / true_depth[~on_cube]).median()) < 1.5  # and not at infinity
    assert float((depth[on_cube] - true_depth[on_cube]).abs().median()) < 0.5  # the cube: in the box


def test_an_optimiser_saved_before_the_outer_grids_loads_into_one_with_them():
    from frugalnerf_ns.run.trainer import with_new_parameters

    a, b, c = (torch.nn.Parameter(torch.randn(3)) for _ in range(3))
    old = torch.optim.Adam([a, b], lr=0.1)
    (a.sum() + 2 * b.sum()).backward()
    old.step()
    saved = {"encodings": old.state_dict()}
    new = torch.optim.Adam([a, b, c], lr=0.1)
    with pytest.raises(ValueError):
        new.load_state_dict(saved["encodings"])  # what nerfstudio's loader would hit
    new.load_state_dict(with_new_parameters(saved, {"encodings": new})["encodings"])
    assert torch.equal(new.state[a]["exp_avg"], old.state[a]["exp_avg"]) and torch.equal(new.state[b]["exp_avg_sq"],
                                                                                        old.state[b]["exp_avg_sq"])
    assert c not in new.state  # fresh moments for the new parameters
    same = torch.optim.Adam([a, b], lr=0.1)
    assert with_new_parameters(saved, {"encodings": same}) == saved  # nothing added: unchanged
