"""The fused density march (NVIDIA Warp, on the CPU) against the torch inference marcher it replaces: the same
pixels, depths and accumulations on fields with and without an alpha mask, ReLU and softplus densities, every
scale, rays that miss the box, start inside it or turn opaque early; and the fallback when Warp is unusable."""

import pytest
import torch

from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.geometry.raymarch import intersect_aabb
from frugalnerf_ns.field import fused_kernels
from frugalnerf_ns.model.rendering import FAINT_BUDGET, render_scale_inference
from frugalnerf_ns.errors import UserError
from tests.marching_scenes import SETTINGS, opaque_field, rays

try:
    import warp  # noqa: F401 - a dependency: where it is installed the kernels must compile (an error fails here)

    wp = fused_kernels.warp_kernels("warp")
except ImportError:
    wp = None
needs_warp = pytest.mark.skipif(wp is None, reason="Warp is not installed")


@pytest.fixture(autouse=True)
def float32_colour(monkeypatch, request):
    """The kernels' arithmetic against torch's, in float32: the bfloat16 colour MLP of CPUs that have it (the
    default with the kernels there) is tested on its own (``test_the_bfloat16_colour_...``)."""
    if "bfloat16" not in request.node.name:
        monkeypatch.setattr("frugalnerf_ns.field.radiance_field.native_bfloat16", lambda: False)


def render(field, scale, kernels, origins=None, directions=None, termination=1e-4, faint_budget=FAINT_BUDGET):
    if origins is None:
        origins, directions = rays(600, seed=3)
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    background = torch.tensor([0.2, 0.5, 1.0])
    return render_scale_inference(field, origins, directions, scale, background, segments, **SETTINGS,
                                  termination=termination, faint_budget=faint_budget, kernels=kernels)


def close(a, b):
    assert torch.allclose(a.rgb, b.rgb, atol=2e-5), (a.rgb - b.rgb).abs().max()
    assert torch.allclose(a.accumulation, b.accumulation, atol=2e-5)
    assert torch.allclose(a.depth, b.depth, atol=2e-4)


@needs_warp
@pytest.mark.parametrize("mask", [False, True])
@pytest.mark.parametrize("scale", [0, 1, 2])
def test_the_fused_march_renders_the_torch_marchers_pixels(scale, mask):
    field = opaque_field(mask=mask)
    ours, reference = render(field, scale, wp), render(field, scale, None)
    close(ours, reference)
    assert reference.accumulation.max() > 0.999 and reference.accumulation[:20].abs().max() == 0
    # Without termination and faint budget too (every sample to the end of its segment).
    close(render(field, scale, wp, termination=0.0, faint_budget=0.0), render(field, scale, None, termination=0.0,
                                                                             faint_budget=0.0))


@needs_warp
def test_rays_that_all_miss_the_box_and_no_rays_at_all():
    field = opaque_field(mask=True)
    origins = torch.tensor([[0.0, 0.0, 2.5]]).repeat(10, 1)
    away = torch.tensor([[0.0, 0.0, 1.0]]).repeat(10, 1)
    ours = render(field, 0, wp, origins, away)
    close(ours, render(field, 0, None, origins, away))
    assert torch.equal(ours.rgb, torch.tensor([[0.2, 0.5, 1.0]]).repeat(10, 1))  # the background alone
    assert render(field, 0, wp, origins[:0], away[:0]).rgb.shape == (0, 3)


@needs_warp
def test_softplus_density_rays_from_inside_the_box_and_a_hazy_field():
    torch.manual_seed(4)
    field = FrugalNeRFField(torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]]), (20, 22, 18),
                            density_components=(3, 2, 2), appearance_components=(4, 2, 2), mlp_hidden_dim=16,
                            mlp_implementation="torch", density_activation="softplus")
    with torch.no_grad():
        for tensor in [*field.density_grid.planes, *field.density_grid.lines]:
            tensor.uniform_(0.2, 1.7)  # a haze: accumulations 0.04-0.997, some rays terminate
    generator = torch.Generator().manual_seed(5)
    origins = torch.rand(500, 3, generator=generator) * 1.6 - 0.8  # inside the box
    directions = torch.nn.functional.normalize(torch.randn(500, 3, generator=generator), dim=-1)
    ours, reference = (render(field, 0, k, origins, directions) for k in (wp, None))
    close(ours, reference)
    assert 0.3 < float(reference.accumulation.mean()) < 0.9 and float(reference.accumulation.max()) > 0.99


@needs_warp
def test_the_model_renders_with_the_kernels_by_default_and_matches_torch():
    from tests.helpers import tiny_model

    model = tiny_model()
    model.eval()
    assert model.config.kernels == "auto"
    origins, directions = rays(400, seed=6)
    field = model.field
    with torch.no_grad():
        for line in field.density_grid.lines:
            line.add_(0.4)
    ours, reference = render(field, 0, wp, origins, directions), render(field, 0, None, origins, directions)
    close(ours, reference)


def test_without_warp_auto_falls_back_to_torch_with_one_line_and_warp_is_an_option_error(monkeypatch):
    said = []
    monkeypatch.setattr(fused_kernels, "_state", {})

    def broken(say):
        raise RuntimeError("no compiler here\nsecond line")

    monkeypatch.setattr(fused_kernels, "_load_warp", broken)
    assert fused_kernels.warp_kernels("auto", said.append) is None
    assert said == ["frugalnerf: fused kernels unavailable (RuntimeError: no compiler here): rendering with the torch "
                    "path"]
    assert fused_kernels.warp_kernels("auto", said.append) is None and len(said) == 1  # said once per process
    with pytest.raises(UserError, match="--pipeline.model.kernels warp: Warp cannot be used here"):
        fused_kernels.warp_kernels("warp", said.append)
    assert fused_kernels.warp_kernels("torch", said.append) is None


@needs_warp
def test_the_fused_outer_space_composites_as_torch_does():
    from frugalnerf_ns.field.outer_space import OuterSpace

    torch.manual_seed(7)
    outer = OuterSpace(torch.tensor([[-1.0, -0.5, -1.0], [1.0, 0.5, 1.0]]), 24, 4, 4, 32, 16)
    with torch.no_grad():
        for tensor in [*outer.density_grid.planes, *outer.density_grid.lines]:
            tensor.uniform_(0.0, 0.6)
        for tensor in [*outer.appearance_grid.planes, *outer.appearance_grid.lines]:
            tensor.normal_(0.0, 0.5)
    generator = torch.Generator().manual_seed(8)
    # Cameras outside the box looking at it (front and behind samples), and some inside it (behind only).
    origins = torch.cat([torch.randn(300, 3, generator=generator) * 0.3 + torch.tensor([0.0, 0.0, 4.0]),
                         torch.rand(100, 3, generator=generator) - 0.5])
    directions = torch.nn.functional.normalize(torch.randn(400, 3, generator=generator) * 0.4
                                               + torch.tensor([0.0, 0.0, -1.0]), dim=-1)
    with torch.no_grad():
        ours, reference = outer.render(origins, directions, False, 0.0, wp), outer.render(origins, directions, False)
    for a, b in zip(ours, reference):  # front, behind
        assert torch.allclose(a.rgb, b.rgb, atol=2e-5) and torch.allclose(a.accumulation, b.accumulation, atol=2e-5)
        assert torch.allclose(a.depth, b.depth, rtol=1e-4)
    assert 0.05 < float(reference[0].accumulation.mean()) < 0.95 and float(reference[1].accumulation.mean()) > 0.05


@needs_warp
@pytest.mark.parametrize("stretched", [False, True])
@pytest.mark.parametrize("scale", [0, 1, 2])
def test_the_fused_feature_read_gives_the_planes_colours(scale, stretched, monkeypatch):
    from frugalnerf_ns.field import radiance_field

    field = FrugalNeRFField(AABB_FEATURES, (21, 26, 19), density_components=(2, 2, 2), appearance_components=(5, 3, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch", lower_scale_reading="stretched" if stretched
                            else "aligned")
    with torch.no_grad():
        for tensor in [*field.appearance_grid.planes, *field.appearance_grid.lines]:
            tensor.normal_(0.0, 1.5)
    monkeypatch.setattr(radiance_field, "BAKED_FEATURES_MAX_ENTRIES", 0)  # as a grid too large to bake
    assert field.baked_features(scale) is None
    generator = torch.Generator().manual_seed(9)
    positions = (torch.rand(3000, 3, generator=generator) * 2.4 - 1.2) * AABB_FEATURES[1]  # some beyond the box
    directions = torch.nn.functional.normalize(torch.randn(3000, 3, generator=generator), dim=-1)
    with torch.no_grad():
        ours = field.inference_color(positions, directions, scale, wp)
        reference = field.color(positions, directions, scale)
        assert torch.allclose(ours, reference, atol=1e-5)
        # The features the kernel reads, against the planes' and lines' reads they replace.
        coords = field.normalize(positions)
        products = torch.cat(field.appearance_grid.plane_line_products(coords, field.stride(scale), stretched), dim=-1)
        key = ("channels last", field.stride(scale))
        mapped = field.appearance_grid.view_coords(coords, field.stride(scale), stretched)
        fused = fused_kernels.vm_features(wp, field._channels_last[key][1], mapped)
        assert torch.allclose(fused, products, atol=1e-5) and float(products.std()) > 0.5
        # A parameter changed after the first read: the channels-last copies follow it.
        for plane in field.appearance_grid.planes:
            plane.normal_(0.0, 1.5)
        assert torch.allclose(field.inference_color(positions, directions, scale, wp),
                              field.color(positions, directions, scale), atol=1e-5)
        assert not torch.allclose(fused_kernels.vm_features(wp, field._channels_last[key][1], mapped), fused, atol=0.1)


AABB_FEATURES = torch.tensor([[-1.0, -0.8, -1.2], [1.0, 0.8, 1.2]])


@needs_warp
def test_the_bfloat16_colour_mlp_stays_within_a_255th_of_float32(monkeypatch):
    from frugalnerf_ns.field.color_mlp import ColorMLP
    from tests.helpers import tiny_model

    torch.manual_seed(0)
    mlp = ColorMLP(27, hidden_dim=128, implementation="torch")
    features = torch.randn(20000, 27) * 2.0
    full, low = mlp(features), mlp.forward_bfloat16(features)
    assert low.dtype == torch.float32 and low.shape == full.shape
    difference = float((low - full).abs().max())
    assert 0 < difference < 1 / 255  # rounded, not the same numbers, but below one step of an 8-bit image
    # The model's renders with the kernels and a bfloat16 MLP (forced here: the default where the CPU has it)
    # against the float32 torch path.
    monkeypatch.setattr("frugalnerf_ns.field.radiance_field.native_bfloat16", lambda: True)
    model = tiny_model()
    model.eval()
    with torch.no_grad():
        for line in model.field.density_grid.lines:
            line.add_(0.4)
        for tensor in [*model.field.appearance_grid.planes, *model.field.appearance_grid.lines]:
            tensor.normal_(0.0, 1.0)
    origins, directions = rays(400, seed=6)
    ours, reference = render(model.field, 0, wp, origins, directions), render(model.field, 0, None, origins, directions)
    largest = float((ours.rgb - reference.rgb).abs().max())
    psnr = -10 * torch.log10(((ours.rgb - reference.rgb) ** 2).mean())
    assert 0 < largest < 1 / 255 and float(psnr) > 50, (largest, float(psnr))
