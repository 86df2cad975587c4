"""The fused training density read (NVIDIA Warp, on the CPU) against the torch reads of the planes and lines it
replaces: values and every plane's and line's gradient, at every stride, aligned and stretched, with points beyond
the box, grids the strides do not divide, one-entry axes and gradients that are zero; split over the cores as in one
launch; and the fallback where the kernels do not compile."""

import pytest
import torch

from frugalnerf_ns.field import fused_density, fused_kernels
from frugalnerf_ns.field.tensorial import TensorVMGrid

try:
    import warp  # noqa: F401 - a dependency: where it is installed the kernels must compile (an error fails here)

    wp = fused_kernels.warp_kernels("warp")
except ImportError:
    wp = None
needs_warp = pytest.mark.skipif(wp is None, reason="Warp is not installed")


def grid_and_points(resolution, components, n=3000, seed=0):
    torch.manual_seed(seed)
    grid = TensorVMGrid(resolution, components, init_scale=0.5)
    coords = torch.rand(n, 3) * 2.4 - 1.2  # a sixth of them beyond a face of the box: border-clamped reads
    return grid, coords


def torch_read(grid, coords, stride, stretched, weights):
    """Density and gradients from the float64 torch reads (the reference)."""
    for tensor in grid.parameters():
        tensor.grad = None
    grid64 = TensorVMGrid(grid.resolution_tuple, grid.components).double()
    grid64.load_state_dict({k: v.double() for k, v in grid.state_dict().items()})
    raw = sum(p.sum(dim=-1) for p in grid64.plane_line_products(coords.double(), stride, stretched))
    raw.backward(weights.double())
    return raw.detach(), [t.grad for t in [*grid64.planes, *grid64.lines]]


def fused_read(grid, coords, stride, stretched, weights):
    for tensor in grid.parameters():
        tensor.grad = None
    raw = fused_density.fused_density(wp, grid, grid.view_coords(coords, stride, stretched), stride)
    raw.backward(weights)
    return raw, [t.grad for t in [*grid.planes, *grid.lines]]


def assert_same(ours, reference):
    raw, grads = ours
    raw_ref, grads_ref = reference
    assert raw.dtype == torch.float32 and raw.shape == raw_ref.shape
    assert torch.allclose(raw.double(), raw_ref, rtol=1e-5, atol=1e-5 * float(raw_ref.abs().max()))
    assert len(grads) == len(grads_ref) == 6
    for grad, grad_ref in zip(grads, grads_ref):
        assert grad.shape == grad_ref.shape and grad.dtype == torch.float32
        scale = float(grad_ref.abs().max())
        assert scale > 0
        assert torch.allclose(grad.double(), grad_ref, rtol=1e-5, atol=1e-5 * scale), (grad.double() - grad_ref).abs().max()


@needs_warp
@pytest.mark.parametrize("stretched", [False, True])
@pytest.mark.parametrize("stride", [1, 2, 4, 16])
def test_the_fused_density_read_gives_the_planes_values_and_gradients(stride, stretched):
    grid, coords = grid_and_points((23, 30, 17), (5, 3, 2))  # 23, 30, 17: no stride above 1 divides them all
    weights = torch.randn(coords.shape[0])
    weights[::3] = 0.0  # samples that no loss reads (or that ReLU cut) add nothing
    assert_same(fused_read(grid, coords, stride, stretched, weights), torch_read(grid, coords, stride, stretched, weights))


@needs_warp
def test_a_one_entry_axis_and_no_points():
    grid, coords = grid_and_points((9, 1, 12), (2, 2, 3), n=500)
    weights = torch.randn(coords.shape[0])
    ours, reference = fused_read(grid, coords, 1, False, weights), torch_read(grid, coords, 1, False, weights)
    assert_same(ours, reference)
    empty = fused_density.fused_density(wp, grid, coords[:0], 1)
    assert empty.shape == (0,)


@needs_warp
def test_reads_split_over_the_cores_equal_one_launch(monkeypatch):
    grid, coords = grid_and_points((40, 36, 30), (4, 2, 2), n=fused_density.SPLIT_MIN_SAMPLES + 5000)
    weights = torch.randn(coords.shape[0])
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)
    one_raw, one_grads = fused_read(grid, coords, 2, False, weights)
    one_grads = [g.clone() for g in one_grads]
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert len(fused_kernels._parts(coords.shape[0], fused_density.SPLIT_MIN_SAMPLES)) == 3
    raw, grads = fused_read(grid, coords, 2, False, weights)
    assert torch.equal(raw, one_raw)  # each point is read on its own
    for grad, one in zip(grads, one_grads):  # three tables summed: float rounding
        assert torch.allclose(grad, one, rtol=1e-5, atol=1e-6 * float(one.abs().max()))


@needs_warp
def test_a_read_that_does_not_compile_falls_back_to_torch_with_one_line(monkeypatch):
    from frugalnerf_ns.field.radiance_field import FrugalNeRFField

    def broken(wp_module, components):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(fused_kernels, "_state", {**fused_kernels._state})
    fused_kernels._state.pop(("density_read", (3, 2, 2)), None)
    monkeypatch.setattr(fused_density, "define_density_read", broken)
    said = []
    assert fused_density.fused_density(wp, TensorVMGrid((8, 8, 8), (3, 2, 2)), torch.zeros(4, 3), 1, said.append) is None
    assert said == ["frugalnerf: fused training density read for (3, 2, 2) channels unavailable (RuntimeError: no "
                    "compiler here): reading the planes with torch"]
    field = FrugalNeRFField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), (8, 8, 8), density_components=(3, 2, 2),
                            appearance_components=(2, 2, 2), mlp_hidden_dim=8, mlp_implementation="torch")
    points = torch.rand(50, 3) * 2 - 1
    reference = field.density(points)
    with field.fused_density_reads(wp):
        assert torch.equal(field.density(points), reference)  # the torch reads, the same numbers
    assert field._density_kernels is None


@needs_warp
def test_a_fields_reads_within_a_block_share_one_copy_of_the_planes_and_a_new_block_sees_new_values():
    """A training step's forward pass reads the planes' channels-last copies made at its first read; the next step
    (after the optimiser's update in place: fused Adam does not bump a tensor's version) makes new ones."""
    from frugalnerf_ns.field.radiance_field import FrugalNeRFField

    torch.manual_seed(3)
    field = FrugalNeRFField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), (12, 14, 10),
                            density_components=(3, 2, 2), appearance_components=(2, 2, 2), mlp_hidden_dim=8,
                            mlp_implementation="torch")
    optimiser = torch.optim.Adam(field.density_grid.parameters(), lr=0.1, fused=True)
    points = torch.rand(400, 3) * 2 - 1
    made = []
    tables = fused_density._tables
    for step in range(2):
        reference = [field.density(points, scale).detach() for scale in range(3)]  # torch: outside the block
        with field.fused_density_reads(wp):
            fused_density._tables = lambda *a: made.append(1) or tables(*a)
            try:
                densities = [field.density(points, scale) for scale in range(3)]
            finally:
                fused_density._tables = tables
        assert len(made) == step + 1  # one copy per block, for its three scales
        for ours, expected in zip(densities, reference):
            assert torch.allclose(ours.detach(), expected, rtol=1e-5, atol=1e-5)
        sum(d.sum() for d in densities).backward()
        optimiser.step()
        optimiser.zero_grad()
    assert field._density_tables is None
