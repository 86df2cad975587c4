import math

import pytest
import torch
import torch.nn.functional as F

from frugalnerf_ns.field.grid_sizes import log_linear_voxel_counts, resolution_for_voxels
from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.field.tensorial import TensorVMGrid, coords_for_stride, read_node_sum, strided_length

AABB = torch.tensor([[-1.0, -1.5, -0.5], [1.0, 1.5, 0.5]])


def test_planes_and_lines_have_per_plane_components_and_non_cubic_resolution():
    grid = TensorVMGrid((17, 33, 9), (16, 4, 4))
    shapes = [tuple(p.shape) for p in grid.planes] + [tuple(line.shape) for line in grid.lines]
    # XY (H=y, W=x), XZ, YZ planes; Z, Y, X lines.
    assert shapes == [(1, 16, 33, 17), (1, 4, 9, 17), (1, 4, 9, 33), (1, 16, 9, 1), (1, 4, 33, 1), (1, 4, 17, 1)]
    products = grid.plane_line_products(torch.rand(10, 3) * 2 - 1)
    assert [tuple(p.shape) for p in products] == [(10, 16), (10, 4), (10, 4)]


def test_lower_scales_are_views_of_the_same_storage():
    grid = TensorVMGrid((33, 33, 33), (4, 2, 2))
    planes, lines = grid.scale_views(4)
    for view, full in zip(planes + lines, list(grid.planes) + list(grid.lines)):
        assert view.untyped_storage().data_ptr() == full.untyped_storage().data_ptr()
    assert tuple(planes[0].shape) == (1, 4, 9, 9) and tuple(lines[0].shape) == (1, 4, 9, 1)


def test_gradient_through_a_lower_scale_reaches_only_the_shared_full_resolution_entries():
    grid = TensorVMGrid((33, 33, 33), (2, 2, 2))
    grid.plane_line_products(torch.rand(64, 3) * 2 - 1, stride=4)[0].sum().backward()
    grad = grid.planes[0].grad[0, 0]
    on_stride = torch.zeros_like(grad, dtype=torch.bool)
    on_stride[::4, ::4] = True
    assert grad[on_stride].abs().sum() > 0
    assert grad[~on_stride].abs().sum() == 0


def test_strided_coordinates_read_the_same_world_point():
    # A node of the view (index k) is full-grid node k * stride: both lookups must agree there.
    grid = TensorVMGrid((37, 21, 29), (3, 3, 3))
    res = grid.resolution_tuple
    nodes = torch.tensor([[8, 4, 12], [0, 0, 0], [36, 20, 28], [32, 16, 24]], dtype=torch.float32)
    stride = 4
    nodes = (nodes / stride).floor() * stride  # on the view's lattice
    coords = nodes / (torch.tensor(res) - 1) * 2 - 1
    full = grid.plane_line_products(coords, stride=1)
    lower = grid.plane_line_products(coords, stride=stride)
    for a, b in zip(full, lower):
        torch.testing.assert_close(a, b)
    assert strided_length(37, 4) == 10
    assert coords_for_stride(torch.tensor(-1.0), 37, 4) == -1.0


def test_model_size_does_not_grow_with_the_number_of_scales():
    sizes = []
    for lower in range(4):
        field = FrugalNeRFField(AABB, (20, 30, 10), num_lower_scales=lower, mlp_implementation="torch")
        sizes.append(sum(p.numel() for p in field.parameters()))
        assert field.num_scales == lower + 1
    assert len(set(sizes)) == 1


def test_upsampling_keeps_the_represented_function():
    grid = TensorVMGrid((9, 7, 5), (3, 2, 2))
    coords = torch.rand(500, 3) * 2 - 1
    before = [p.detach() for p in grid.plane_line_products(coords)]
    grid.resample((17, 13, 9))  # refinement by 2: every old node is a new node, bilinear is exact
    after = grid.plane_line_products(coords)
    for a, b in zip(before, after):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
    assert grid.resolution_tuple == (17, 13, 9)


def test_crop_keeps_values_inside_the_kept_region():
    grid = TensorVMGrid((11, 11, 11), (2, 2, 2))
    full_plane = grid.planes[0].detach().clone()
    grid.crop((2, 3, 1), (8, 9, 10))
    assert grid.resolution_tuple == (7, 7, 10)
    torch.testing.assert_close(grid.planes[0].detach(), full_plane[:, :, 3:10, 2:9])


def test_state_dict_loads_into_a_grid_of_another_resolution():
    trained = TensorVMGrid((21, 21, 21), (2, 2, 2))
    fresh = TensorVMGrid((5, 5, 5), (2, 2, 2))
    fresh.load_state_dict(trained.state_dict())
    assert fresh.resolution_tuple == (21, 21, 21)
    coords = torch.rand(20, 3) * 2 - 1
    torch.testing.assert_close(fresh.plane_line_products(coords)[1], trained.plane_line_products(coords)[1])


def test_voxel_schedule_is_log_linear_and_resolution_follows_the_box():
    counts = log_linear_voxel_counts(64**3, 640**3, 5)
    assert counts[-1] == 640**3
    ratios = [b / a for a, b in zip([64**3] + counts[:-1], counts)]
    assert max(ratios) / min(ratios) == pytest.approx(1.0, rel=1e-3)
    res = resolution_for_voxels(1000, (1.0, 2.0, 4.0))
    assert res == (5, 10, 20)
    assert math.prod(res) == 1000


def test_span_stride_gives_lower_scale_views_that_end_on_the_far_face():
    box = (2.0, 2.2, 1.33)
    plain = resolution_for_voxels(160**3, box)
    spanning = resolution_for_voxels(160**3, box, span_stride=16)
    for r, r16 in zip(plain, spanning):
        assert (r16 - 1) % 16 == 0 and abs(r16 - r) <= 8
    # The coarsest view's last entry is the full grid's last entry: it reaches the far face.
    for r16 in spanning:
        assert (strided_length(r16, 16) - 1) * 16 == r16 - 1
    assert any((strided_length(r, 16) - 1) * 16 < r - 1 for r in plain)
    # A far-face point reads the far entry at every scale.
    far = torch.ones(1, 3)
    for stride in (1, 4, 16):
        assert torch.allclose(
            torch.stack([coords_for_stride(far[:, i], spanning[i], stride) for i in range(3)]), torch.ones(3, 1)
        )
    # Tiny counts keep at least one coarse interval per axis.
    assert resolution_for_voxels(8, (1.0, 1.0, 1.0), span_stride=16) == (17, 17, 17)
    # The nearest such sizes: LLFF's NDC box's first 32^3 grid (35x39x23) keeps 59 % of its voxels.
    assert resolution_for_voxels(32**3, (3.0, 3.34, 2.0), span_stride=16) == (33, 33, 17)


def test_sample_step_is_half_a_voxel_and_coarser_by_the_ratio_at_lower_scales():
    field = FrugalNeRFField(AABB, (21, 31, 11), mlp_implementation="torch")
    voxel = 0.1  # box 2 x 3 x 1 with 20 x 30 x 10 intervals
    assert field.sample_step(0) == pytest.approx(voxel / 2)
    assert field.sample_step(1) == pytest.approx(4 * voxel / 2)
    assert field.sample_step(2) == pytest.approx(16 * voxel / 2)


def test_alpha_mask_and_shrink_fit_the_occupied_region():
    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (21, 21, 21), density_activation="relu",
                            mlp_implementation="torch")
    with torch.no_grad():
        for p in list(field.density_grid.planes) + list(field.density_grid.lines):
            p.zero_()
        # Density only where x is in the upper half: the XY plane's columns x >= 0 times a constant Z line.
        field.density_grid.planes[0][:, 0, :, 11:] = 1.0
        field.density_grid.lines[0][:, 0] = 1.0
    box = field.update_alpha_mask(step_ratio=0.5, distance_scale=25.0)
    assert box[0, 0] >= -0.05 and box[0, 0] <= 0.05  # dilation reaches one voxel (0.1) left of x = 0.1
    assert box[1, 0] == pytest.approx(1.0)
    inside = field.inside(torch.tensor([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]]))
    assert inside.tolist() == [True, False]
    field.shrink(box)
    assert field.aabb[0, 0] >= -0.1 and field.aabb[1, 0] == pytest.approx(1.0)
    assert field.density_grid.resolution_tuple[0] < 21


def test_the_alpha_mask_empties_what_no_training_camera_sees():
    """``seen``: a camera at x = -3 looking along +x with a narrow view sees the box's middle only; the alpha mask
    keeps density there (and one node around it) and empties the rest, though every node holds the same density."""
    from frugalnerf_ns.geometry.scene_analysis import views_seeing

    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (21, 21, 21), density_activation="relu",
                            mlp_implementation="torch")
    with torch.no_grad():
        for p in list(field.density_grid.planes) + list(field.density_grid.lines):
            p.zero_()
        field.density_grid.planes[0][:, 0] = 1.0
        field.density_grid.lines[0][:, 0] = 1.0
    # OpenGL camera (looks along its -z): its -z axis is world +x, its image 20 px wide at focal 80 (14 degrees).
    c2w = torch.tensor([[[0.0, 0.0, -1.0, -3.0], [0.0, 1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]]])
    intrinsics = torch.tensor([[80.0, 80.0, 10.0, 10.0]])
    probes = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.9, 0.0], [0.0, 0.0, 0.9], [-3.5, 0.0, 0.0]])
    assert views_seeing(probes, c2w, intrinsics, (20, 20)).tolist() == [1, 0, 0, 0]  # behind the camera: not seen
    full = field.update_alpha_mask(step_ratio=0.5, distance_scale=25.0).clone()
    assert bool(field.alpha_mask.all())
    carved = field.update_alpha_mask(0.5, 25.0, seen=lambda p: views_seeing(p, c2w, intrinsics, (20, 20)) > 0)
    assert field.inside(probes[:3]).tolist() == [True, False, False]
    assert 0.0 < float(field.alpha_mask.float().mean()) < 0.5
    assert (carved[1] - carved[0] < full[1] - full[0]).any()


def test_inside_is_the_box_test_and_the_nearest_mask_voxel_of_the_masks_own_box():
    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (20, 24, 16), mlp_implementation="torch")
    # The mask's box differs from the field's (as after a shrink): points in one and not the other, and points
    # beyond the mask's box on one axis only, whose clamped voxel would be occupied.
    field.alpha_mask_aabb = torch.tensor([[-1.0, -0.9, -1.1], [0.9, 1.0, 1.0]])
    points = torch.rand(200000, 3, generator=torch.Generator().manual_seed(0)) * 2.6 - 1.3

    def by_definition(mask):
        box = ((points >= field.aabb[0]) & (points <= field.aabb[1])).all(dim=-1)
        res = torch.tensor(mask.shape)
        lo, hi = field.alpha_mask_aabb
        idx = ((points - lo) / (hi - lo) * (res - 1)).round().long()
        in_mask_box = ((idx >= 0) & (idx < res)).all(dim=-1)
        idx = torch.minimum(idx.clamp_min(0), res - 1)
        return box & in_mask_box & mask[idx[:, 0], idx[:, 1], idx[:, 2]]

    for density in (0.5, 0.9):  # a second mask after the first was looked up: the cached volume follows it
        field.alpha_mask = torch.rand(20, 24, 16, generator=torch.Generator().manual_seed(1)) < density
        expected = by_definition(field.alpha_mask)
        assert 0.1 < expected.float().mean() < 0.9
        assert torch.equal(field.inside(points), expected)
        assert torch.equal(field.inside(points.view(400, 500, 3)), expected.view(400, 500))
    field.alpha_mask[:] = True  # changed in place
    assert torch.equal(field.inside(points), by_definition(field.alpha_mask))
    odd = torch.tensor([[float("nan"), 0.0, 0.0], [float("inf"), 0.0, 0.0], [0.0, -float("inf"), 0.0], [1e30, 0, 0]])
    assert field.inside(odd).tolist() == [False] * 4


@pytest.mark.parametrize("shape", [(1, 5, 7, 9), (1, 3, 6, 1), (1, 2, 1, 4), (1, 4, 1, 1)])
def test_cpu_sampling_matches_grid_sample_values_and_gradients(shape):
    """The CPU backward (index_add over four corners) equals grid_sample's, border and strided views included."""
    import torch.nn.functional as F

    from frugalnerf_ns.field.tensorial import sample_plane

    torch.manual_seed(0)
    full = torch.randn(shape[0], shape[1], shape[2] * 2, shape[3] * 2, dtype=torch.float64, requires_grad=True)
    plane = full[:, :, ::2, ::2]  # a strided scale view, as the lower scales read
    coords = torch.cat([torch.rand(200, 2, dtype=torch.float64) * 2.4 - 1.2,  # beyond the border too
                        torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [0.0, 1.0]], dtype=torch.float64)])
    weights = torch.randn(shape[1], len(coords), dtype=torch.float64)
    ours = sample_plane(plane, coords[:, 0], coords[:, 1])
    (ours * weights).sum().backward()
    ours_grad, full.grad = full.grad.clone(), None
    reference = F.grid_sample(plane, coords.view(1, -1, 1, 2), mode="bilinear", padding_mode="border", align_corners=True)
    (reference.view(shape[1], -1) * weights).sum().backward()
    assert torch.allclose(ours, reference.view(shape[1], -1), atol=1e-12)
    assert torch.allclose(ours_grad, full.grad, atol=1e-12)



def density_where_inside(field, points, scale=0):
    """The reference: the planes' density where ``inside`` holds, 0 elsewhere."""
    return torch.where(field.inside(points), field.density(points, scale), torch.zeros(points.shape[0]))


# The mask multiplies the activated density, whichever the activation: one masked case suffices.
@pytest.mark.parametrize("activation, mask", [("relu", False), ("softplus", False), ("relu", True)])
def test_baked_density_reads_what_the_planes_and_lines_give_where_occupied_at_every_scale(activation, mask):
    # Resolutions that are not 4k+1 or 16k+1: the lower scales' views stop short of the far faces there, and
    # points beyond read the border entry in both paths. Points reach outside the box (density 0 there).
    torch.manual_seed(0)
    aabb = torch.tensor([[-1.0, -0.5, -2.0], [1.5, 0.5, 1.0]])
    field = FrugalNeRFField(aabb, (23, 10, 30), density_components=(5, 3, 2), appearance_components=(2, 2, 2),
                            density_activation=activation, mlp_implementation="torch")
    with torch.no_grad():
        if mask:  # empty one corner, so the mask leaves it out; then shrink, so the mask's box is the larger
            for plane in field.density_grid.planes:
                plane[:, :, :6, :6] = -5.0
            field.shrink(field.update_alpha_mask(0.5, 25.0, threshold=0.05))
            assert 0.05 < field.alpha_mask.float().mean() < 0.95
    points = aabb[0] + torch.rand(6000, 3) * (aabb[1] - aabb[0]) * 1.1 - 0.05 * (aabb[1] - aabb[0])
    with torch.no_grad():
        assert 0.1 < field.inside(points).float().mean() < 0.9
        for scale in range(field.num_scales):
            reference = density_where_inside(field, points, scale)
            baked = field.occupied_density(points, scale)
            assert baked.shape == reference.shape
            assert torch.allclose(baked, reference, atol=1e-5, rtol=1e-5), (scale, (baked - reference).abs().max())
            # The colour path outside training reads the baked appearance features at the same points.
            directions = torch.nn.functional.normalize(torch.randn(points.shape[0], 3), dim=-1)
            torch.testing.assert_close(field.inference_color(points, directions, scale), field.color(points, directions, scale),
                                       atol=1e-5, rtol=1e-5)


def test_baked_density_follows_an_optimiser_step_and_a_resize():
    torch.manual_seed(1)
    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (12, 12, 12), density_components=(2, 2, 2),
                            appearance_components=(2, 2, 2), mlp_implementation="torch")
    points = torch.rand(500, 3) * 2 - 1
    optimizer = torch.optim.Adam(field.density_grid.parameters(), lr=0.1)
    with torch.no_grad():
        before = field.occupied_density(points).clone()
    field.density(points).sum().backward()
    optimizer.step()  # in place: the baked tensor is stale now
    with torch.no_grad():
        after = field.occupied_density(points)
        assert not torch.allclose(after, before)
        assert torch.allclose(after, field.density(points), atol=1e-5)
        field.upsample((17, 15, 13))
        assert torch.allclose(field.occupied_density(points), field.density(points), atol=1e-5)
        field.update_alpha_mask(0.5, 25.0, threshold=0.5)  # a new mask: empty voxels read 0 from now on
        assert torch.allclose(field.occupied_density(points), density_where_inside(field, points), atol=1e-5)



@pytest.mark.parametrize("stride", [1, 3, 4])
@pytest.mark.parametrize("shape", [(1, 5, 13, 10), (1, 3, 7, 1), (1, 2, 1, 9)])
def test_strided_reads_add_their_gradient_into_the_full_tensor(shape, stride):
    """sample_plane / sample_line with a stride read the full tensor's stride view (values and gradients equal to
    grid_sample on the view, its backward through the view's slicing), sizes that the stride does not divide."""
    from frugalnerf_ns.field.tensorial import sample_line, sample_plane

    torch.manual_seed(stride)
    full = torch.randn(*shape, dtype=torch.float64, requires_grad=True)
    line = torch.randn(1, shape[1], shape[2], 1, dtype=torch.float64, requires_grad=True)
    coords = torch.cat([torch.rand(300, 2, dtype=torch.float64) * 2.4 - 1.2,
                        torch.tensor([[-1.0, -1.0], [1.0, 1.0], [1.0, -1.0], [0.0, 1.0]], dtype=torch.float64)])
    weights = torch.randn(2, shape[1], len(coords), dtype=torch.float64)
    ours = (sample_plane(full, coords[:, 0], coords[:, 1], stride), sample_line(line, coords[:, 1], stride))
    sum((o * w).sum() for o, w in zip(ours, weights)).backward()
    ours_grads, full.grad, line.grad = (full.grad.clone(), line.grad.clone()), None, None
    plane_view, line_view = full[:, :, ::stride, ::stride], line[:, :, ::stride, :]
    reference = (F.grid_sample(plane_view, coords.view(1, -1, 1, 2), mode="bilinear", padding_mode="border",
                               align_corners=True).view(shape[1], -1),
                 F.grid_sample(line_view, torch.stack([torch.zeros_like(coords[:, 1]), coords[:, 1]], -1).view(1, -1, 1, 2),
                               mode="bilinear", padding_mode="border", align_corners=True).view(shape[1], -1))
    sum((r * w).sum() for r, w in zip(reference, weights)).backward()
    for a, b in zip(ours, reference):
        assert torch.allclose(a, b, atol=1e-12)
    for a, b in zip(ours_grads, (full.grad, line.grad)):
        assert torch.allclose(a, b, atol=1e-12)
    if stride > 1 and shape[2] > 1:  # entries between the view's rows get nothing
        assert ours_grads[0][:, :, 1::stride].abs().max() == 0 and ours_grads[1][:, :, 1::stride].abs().max() == 0


@pytest.mark.parametrize("channels, length", [(5, 9), (3, 2), (2, 1)])
def test_cpu_line_reads_match_grid_sample_values_and_gradients(channels, length):
    """A line's two-corner read and gradient (sample_line) equal grid_sample's on the [1, C, L, 1] tensor."""
    from frugalnerf_ns.field.tensorial import sample_line

    torch.manual_seed(0)
    full = torch.randn(1, channels, length * 2, 1, dtype=torch.float64, requires_grad=True)
    line = full[:, :, ::2, :]  # a strided scale view, as the lower scales read
    y = torch.cat([torch.rand(200, dtype=torch.float64) * 2.4 - 1.2, torch.tensor([-1.0, 1.0, 0.0], dtype=torch.float64)])
    weights = torch.randn(channels, len(y), dtype=torch.float64)
    ours = sample_line(line, y)
    (ours * weights).sum().backward()
    ours_grad, full.grad = full.grad.clone(), None
    grid = torch.stack([torch.zeros_like(y), y], dim=-1).view(1, -1, 1, 2)
    reference = F.grid_sample(line, grid, mode="bilinear", padding_mode="border", align_corners=True).view(channels, -1)
    (reference * weights).sum().backward()
    assert torch.allclose(ours, reference, atol=1e-12)
    assert torch.allclose(ours_grad, full.grad, atol=1e-12)
    assert ours_grad[0, :, 1::2].abs().max() == 0  # only the view's entries receive gradient


def _einsum_node_sum(grid):
    (p_xy, p_xz, p_yz), (l_z, l_y, l_x) = [p[0] for p in grid.planes], [line[0, :, :, 0] for line in grid.lines]
    return (torch.einsum("cyx,cz->zyx", p_xy, l_z) + torch.einsum("czx,cy->zyx", p_xz, l_y)
            + torch.einsum("czy,cx->zyx", p_yz, l_x))


@pytest.mark.parametrize("resolution", [(33, 33, 17), (20, 23, 11), (2, 5, 3), (17, 1, 5)])
def test_node_sum_matrix_products_match_einsum_values_and_gradients(resolution):
    torch.manual_seed(0)
    grid = TensorVMGrid(resolution, (16, 4, 4)).double()
    weights = torch.randn(resolution[2], resolution[1], resolution[0], dtype=torch.float64)
    reference = _einsum_node_sum(grid)
    nodes = grid.node_sum()
    assert nodes.shape == reference.shape and torch.allclose(nodes, reference, rtol=0, atol=1e-12)
    expected = torch.autograd.grad((reference * weights).sum(), list(grid.parameters()))
    got = torch.autograd.grad((nodes * weights).sum(), list(grid.parameters()))
    for a, b in zip(got, expected):
        assert a.shape == b.shape and b.abs().max() > 0 and torch.allclose(a, b, rtol=0, atol=1e-11)


@pytest.mark.parametrize("resolution", [(33, 33, 17), (20, 23, 11), (2, 5, 3)])
@pytest.mark.parametrize("stride", [1, 4, 16])
def test_node_sum_reads_match_the_planes_values_and_gradients(resolution, stride):
    torch.manual_seed(1)
    grid = TensorVMGrid(resolution, (16, 4, 4)).double()
    points = torch.rand(2000, 3, dtype=torch.float64) * 2.4 - 1.2  # some beyond the box: border clamping
    reference = sum(p.sum(dim=-1) for p in grid.plane_line_products(points, stride))
    weights = torch.randn_like(reference)
    expected = torch.autograd.grad((reference * weights).sum(), list(grid.parameters()))
    values = read_node_sum(grid.node_sum(), points, stride)
    got = torch.autograd.grad((values * weights).sum(), list(grid.parameters()))
    assert torch.allclose(values, reference, rtol=0, atol=1e-12)
    for a, b in zip(got, expected):
        assert torch.allclose(a, b, rtol=0, atol=1e-11)
    assert any(float(b.abs().max()) > 0 for b in expected)


@pytest.mark.parametrize("dtype", [torch.bfloat16, torch.float16])
def test_node_sum_under_autocast_stays_in_the_grids_precision(dtype):
    torch.manual_seed(0)
    grid = TensorVMGrid((9, 7, 5), (16, 4, 4))
    reference = _einsum_node_sum(grid)
    with torch.autocast("cpu", dtype=dtype):
        nodes = grid.node_sum()
    assert nodes.dtype == torch.float32 and torch.allclose(nodes, reference, rtol=1e-5, atol=1e-6)
    nodes.sum().backward()
    assert all(p.grad is not None and p.grad.dtype == torch.float32 for p in grid.parameters())


def test_shared_density_nodes_are_made_with_gradients_and_only_inside_the_block():
    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (9, 9, 9), mlp_implementation="torch")
    points = torch.rand(500, 3) * 2 - 1
    reference = field.density(points, 1)
    with field.shared_density_nodes():
        with torch.no_grad():  # a first read without gradients must not leave gradient-less nodes behind
            assert torch.allclose(field.density(points, 0), field.density(points, 0))
        shared = field.density(points, 1)
        with field.shared_density_nodes(False):  # a block turned off inside reads the planes
            assert field._shared_nodes is None
        assert field._shared_nodes is not None
    assert field._shared_nodes is None
    assert torch.allclose(shared, reference, rtol=1e-5, atol=1e-6)
    shared.sum().backward()
    assert all(p.grad is not None and p.grad.abs().max() > 0 for p in field.density_grid.parameters())


def test_grids_above_the_shared_nodes_limit_read_their_planes_in_training(monkeypatch):
    from frugalnerf_ns.field import radiance_field

    field = FrugalNeRFField(torch.tensor([[-1.0] * 3, [1.0] * 3]), (9, 9, 9), mlp_implementation="torch")
    points = torch.rand(300, 3) * 2 - 1
    monkeypatch.setattr(radiance_field, "SHARED_NODES_MAX_ENTRIES", 9**3)  # the grid itself: still shared
    with field.shared_density_nodes():
        field.density(points, 1)
        assert field._shared_nodes is not None and field._shared_nodes[0] is not None
    monkeypatch.setattr(radiance_field, "SHARED_NODES_MAX_ENTRIES", 9**3 - 1)  # one node fewer: the planes
    with field.shared_density_nodes():
        assert field._shared_nodes is None
        planes = field.density(points, 1)
    assert torch.allclose(planes, field.density(points, 1), rtol=0, atol=0)
