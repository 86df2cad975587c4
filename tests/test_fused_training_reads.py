"""The fused training reads (NVIDIA Warp, on the CPU) against the torch reads of the planes and lines they replace:
density and appearance features, values and every plane's and line's gradient, at every stride, with points
beyond the box, grids the strides do not divide, one-entry axes and gradients that are zero;
several reads of a block adding into one gradient; split over the cores as in one launch; and the fallback where the
kernels do not compile."""

import gc
import weakref

import pytest
import torch

from frugalnerf_ns.field import fused_kernels, fused_training_reads
from frugalnerf_ns.field.tensorial import TensorVMGrid

try:
    import warp  # noqa: F401 - a dependency: where it is installed the kernels must compile (an error fails here)

    wp = fused_kernels.warp_kernels("warp")
except ImportError:
    wp = None
needs_warp = pytest.mark.skipif(wp is None, reason="Warp is not installed")
BOX = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def grid_and_points(resolution, components, n=3000, seed=0):
    torch.manual_seed(seed)
    grid = TensorVMGrid(resolution, components, init_scale=0.5)
    coords = torch.rand(n, 3) * 2.4 - 1.2  # a sixth of them beyond a face of the box: border-clamped reads
    return grid, coords


def torch_reads(grid, reads, features):
    """Values and gradients from the float64 torch reads (the reference): ``reads`` is a list of (coords, stride,
    weights), the gradient that of the sum of every read's weighted values."""
    grid64 = TensorVMGrid(grid.resolution_tuple, grid.components).double()
    grid64.load_state_dict({k: v.double() for k, v in grid.state_dict().items()})
    values, total = [], 0.0
    for coords, stride, weights in reads:
        products = grid64.plane_line_products(coords.double(), stride)
        value = torch.cat(products, dim=-1) if features else sum(p.sum(dim=-1) for p in products)
        values.append(value.detach())
        total = total + (value * weights.double()).sum()
    total.backward()
    return values, [t.grad for t in [*grid64.planes, *grid64.lines]]


def fused_reads(grid, reads, features):
    for tensor in grid.parameters():
        tensor.grad = None
    step = fused_training_reads.StepReads(wp)
    values = [step.read(grid, grid.view_coords(coords, stride), stride, features) for coords, stride, _ in reads]
    sum((value * weights).sum() for value, (_, _, weights) in zip(values, reads)).backward()
    step.close()
    return [v.detach() for v in values], [t.grad for t in [*grid.planes, *grid.lines]]


def assert_same(ours, reference):
    values, grads = ours
    values_ref, grads_ref = reference
    for value, value_ref in zip(values, values_ref):
        assert value.dtype == torch.float32 and value.shape == value_ref.shape
        assert torch.allclose(value.double(), value_ref, rtol=1e-5, atol=1e-5 * float(value_ref.abs().max()))
    assert len(grads) == len(grads_ref) == 6
    for grad, grad_ref in zip(grads, grads_ref):
        assert grad.shape == grad_ref.shape and grad.dtype == torch.float32 and grad.is_contiguous()
        scale = float(grad_ref.abs().max())
        assert scale > 0
        assert torch.allclose(grad.double(), grad_ref, rtol=1e-5, atol=1e-5 * scale), (grad.double() - grad_ref).abs().max()


def weights_for(coords, features, components):
    weights = torch.randn(coords.shape[0], sum(components)) if features else torch.randn(coords.shape[0])
    weights[::3] = 0.0  # samples that no loss reads (or that ReLU cut) add nothing
    return weights


@needs_warp
@pytest.mark.parametrize("features", [False, True])
@pytest.mark.parametrize("stride", [1, 2, 4, 16])
def test_a_fused_read_gives_the_planes_values_and_gradients(stride, features):
    components = (5, 3, 2)
    grid, coords = grid_and_points((23, 30, 17), components)  # 23, 30, 17: no stride above 1 divides them all
    reads = [(coords, stride, weights_for(coords, features, components))]
    assert_same(fused_reads(grid, reads, features), torch_reads(grid, reads, features))


@needs_warp
@pytest.mark.parametrize("features", [False, True])
def test_a_blocks_reads_at_three_strides_add_into_one_gradient(features):
    """A training step's three scales (and more reads of one scale) read one copy and hand the planes one gradient:
    the sum of what each read's torch backward gives."""
    components = (6, 2, 3)
    grid, coords = grid_and_points((31, 22, 27), components, n=4000)
    reads = [(coords[k * 1000:(k + 2) * 1000], stride, weights_for(coords[:2000], features, components))
             for k, stride in enumerate([1, 2, 4])]
    made = []
    tables = fused_training_reads._tables
    fused_training_reads._tables = lambda *a: made.append(1) or tables(*a)
    try:
        ours = fused_reads(grid, reads, features)
    finally:
        fused_training_reads._tables = tables
    assert len(made) == 1
    assert_same(ours, torch_reads(grid, reads, features))


@needs_warp
@pytest.mark.parametrize("features", [False, True])
def test_a_one_entry_axis_and_no_points(features):
    components = (2, 2, 3)
    grid, coords = grid_and_points((9, 1, 12), components, n=500)
    reads = [(coords, 1, weights_for(coords, features, components))]
    assert_same(fused_reads(grid, reads, features), torch_reads(grid, reads, features))
    empty = fused_training_reads.StepReads(wp).read(grid, coords[:0], 1, features)
    assert empty.shape == ((0, 7) if features else (0,))


@needs_warp
@pytest.mark.parametrize("features", [False, True])
def test_reads_split_over_the_cores_equal_one_launch(monkeypatch, features):
    components = (4, 2, 2)
    split = fused_training_reads.SPLIT_MIN_FEATURE_SAMPLES if features else fused_training_reads.SPLIT_MIN_SAMPLES
    grid, coords = grid_and_points((40, 36, 30), components, n=split + 5000)
    reads = [(coords, 2, weights_for(coords, features, components))]
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    (one,), one_grads = fused_reads(grid, reads, features)
    one_grads = [g.clone() for g in one_grads]
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert len(fused_kernels._parts(coords.shape[0], split)) == 3
    (value,), grads = fused_reads(grid, reads, features)
    assert torch.equal(value, one)  # each point is read on its own
    for grad, one_grad in zip(grads, one_grads):  # three tables summed: float rounding
        assert torch.allclose(grad, one_grad, rtol=1e-5, atol=1e-6 * float(one_grad.abs().max()))


@needs_warp
@pytest.mark.parametrize("features", [False, True])
def test_a_plane_gradient_turned_channels_first_in_parts(monkeypatch, features):
    components = (3, 2, 2)
    grid, coords = grid_and_points((210, 190, 9), components, n=5000)  # the XY plane: 39,900 rows
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    assert len(fused_kernels._parts(210 * 190, fused_training_reads.CHANNELS_FIRST_SPLIT_ROWS)) == 2
    reads = [(coords, 1, weights_for(coords, features, components))]
    assert_same(fused_reads(grid, reads, features), torch_reads(grid, reads, features))


@needs_warp
def test_reads_without_gradient_add_none_and_a_closed_block_leaves_nothing_alive():
    grid, coords = grid_and_points((12, 10, 8), (3, 2, 2), n=300)
    step = fused_training_reads.StepReads(wp)
    with torch.no_grad():
        detached = step.read(grid, coords, 1, True)  # the colour of rays whose colour is read detached
    assert not detached.requires_grad
    value = step.read(grid, coords, 2, True)
    reads = weakref.ref(step.grids[id(grid)])
    step.close()
    value.sum().backward()
    assert all(t.grad is not None for t in grid.parameters())
    expected, _ = torch_reads(grid, [(coords, 1, torch.zeros(300, 7))], True)
    assert torch.allclose(detached.double(), expected[0], rtol=1e-5, atol=1e-5)
    gc.disable()  # no cycle may keep the copies and gradient tables: plain reference counting frees them
    try:
        del value, step
        assert reads() is None
    finally:
        gc.enable()


@needs_warp
def test_a_read_that_does_not_compile_falls_back_to_torch_with_one_line(monkeypatch):
    from frugalnerf_ns.field.radiance_field import FrugalNeRFField

    def broken(wp_module, components):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(fused_kernels, "_state", {**fused_kernels._state})
    fused_kernels._state.pop(("grid_reads", (3, 2, 2)), None)
    monkeypatch.setattr(fused_kernels, "define_training_reads", broken)
    said = []
    reads = fused_training_reads.StepReads(wp, said.append)
    assert reads.read(TensorVMGrid((8, 8, 8), (3, 2, 2)), torch.zeros(4, 3), 1, False) is None
    assert said == ["frugalnerf: fused grid reads for (3, 2, 2) channels unavailable (RuntimeError: no "
                    "compiler here): reading the planes with torch"]
    field = FrugalNeRFField(BOX, (8, 8, 8), density_components=(3, 2, 2), appearance_components=(3, 2, 2),
                            mlp_hidden_dim=8, mlp_implementation="torch")
    points, directions = torch.rand(50, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    reference = field.density(points), field.color(points, directions)
    with field.fused_training_reads(wp):
        assert torch.equal(field.density(points), reference[0])  # the torch reads, the same numbers
        assert torch.equal(field.color(points, directions), reference[1])
    assert field._step_reads is None


@needs_warp
def test_a_fields_reads_within_a_block_share_one_copy_per_grid_and_a_new_block_sees_new_values():
    """A training step's forward pass reads each grid's channels-last copies made at its first read; the next step
    (after the optimiser's update in place: fused Adam does not bump a tensor's version) makes new ones. Density and
    colour equal the torch path's, and so do their gradients."""
    from frugalnerf_ns.field.radiance_field import FrugalNeRFField

    torch.manual_seed(3)
    field = FrugalNeRFField(BOX, (12, 14, 10), density_components=(3, 2, 2), appearance_components=(4, 2, 3),
                            mlp_hidden_dim=8, mlp_implementation="torch")
    optimiser = torch.optim.Adam([*field.density_grid.parameters(), *field.appearance_grid.parameters()], lr=0.1,
                                 fused=True)
    points, directions = torch.rand(400, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(400, 3), dim=-1)
    made = []
    tables = fused_training_reads._tables

    def forward():
        values = [field.density(points, scale) for scale in range(3)] + [field.color(points, directions, s) for s in range(3)]
        total = sum(v.sum() for v in values)
        total.backward()
        return [v.detach() for v in values], [t.grad.clone() for t in field.grid_parameters()]

    for step in range(2):
        optimiser.zero_grad()
        reference, reference_grads = forward()  # torch: outside the block
        optimiser.zero_grad()
        with field.fused_training_reads(wp):
            fused_training_reads._tables = lambda *a: made.append(1) or tables(*a)
            try:
                values, grads = forward()
            finally:
                fused_training_reads._tables = tables
        assert len(made) == 2 * (step + 1)  # one copy per grid and block, for its three scales
        for ours, expected in zip(values, reference):
            assert torch.allclose(ours, expected, rtol=1e-5, atol=1e-5)
        for ours, expected in zip(grads, reference_grads):
            assert torch.allclose(ours, expected, rtol=1e-4, atol=1e-5 * float(expected.abs().max()))
        optimiser.step()
    assert field._step_reads is None
