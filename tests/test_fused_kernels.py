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
    assert said == ["frugalnerf: fused kernels unavailable (RuntimeError: no compiler here): rendering and training on "
                    "the torch path"]
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
@pytest.mark.parametrize("scale", [0, 1, 2])
def test_the_fused_feature_read_gives_the_planes_colours(scale, monkeypatch):
    from frugalnerf_ns.field import radiance_field

    field = FrugalNeRFField(AABB_FEATURES, (21, 26, 19), density_components=(2, 2, 2), appearance_components=(5, 3, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch")
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
        products = torch.cat(field.appearance_grid.plane_line_products(coords, field.stride(scale)), dim=-1)
        key = ("channels last", field.stride(scale))
        mapped = field.appearance_grid.view_coords(coords, field.stride(scale))
        fused = fused_kernels.vm_features(wp, field._channels_last[key][1], mapped)
        assert torch.allclose(fused, products, atol=1e-5) and float(products.std()) > 0.5
        # A parameter changed after the first read: the channels-last copies follow it.
        for plane in field.appearance_grid.planes:
            plane.normal_(0.0, 1.5)
        assert torch.allclose(field.inference_color(positions, directions, scale, wp),
                              field.color(positions, directions, scale), atol=1e-5)
        assert not torch.allclose(fused_kernels.vm_features(wp, field._channels_last[key][1], mapped), fused, atol=0.1)


@needs_warp
def test_the_feature_read_is_compiled_for_each_set_of_component_counts():
    from frugalnerf_ns.field.tensorial import TensorVMGrid

    coords = torch.rand(700, 3, generator=torch.Generator().manual_seed(21)) * 2.2 - 1.1
    reads = {}
    for components in [(5, 3, 2), (7, 1, 4), (5, 3, 2)]:
        grid = TensorVMGrid((9, 12, 10), components)
        with torch.no_grad():
            for tensor in [*grid.planes, *grid.lines]:
                tensor.normal_(0.0, 1.0)
            expected = torch.cat(grid.plane_line_products(coords, 1), dim=-1)
            ours = fused_kernels.vm_features(wp, fused_kernels.channels_last(*grid.scale_views(1)), coords)
        assert ours.shape == (700, sum(components)) and torch.allclose(ours, expected, atol=1e-5)
        reads[components] = fused_kernels._state[("grid_reads", components)]
    assert reads[(5, 3, 2)] is not reads[(7, 1, 4)]  # one kernel per set of counts, kept for the next frame


@needs_warp
def test_a_feature_read_that_does_not_compile_falls_back_to_the_planes_read_by_torch(monkeypatch, capsys):
    from frugalnerf_ns.field import radiance_field

    def broken(wp_module, components):
        raise RuntimeError("CPU kernel build failed with error code 1")

    monkeypatch.setattr(fused_kernels, "define_training_reads", broken)
    monkeypatch.setattr(radiance_field, "BAKED_FEATURES_MAX_ENTRIES", 0)
    monkeypatch.setitem(fused_kernels._state, ("grid_reads", (6, 3, 2)), None)
    del fused_kernels._state[("grid_reads", (6, 3, 2))]  # compiled anew here (and forgotten after the test)
    field = FrugalNeRFField(AABB_FEATURES, (21, 26, 19), density_components=(2, 2, 2), appearance_components=(6, 3, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch")
    positions = (torch.rand(500, 3, generator=torch.Generator().manual_seed(3)) * 2 - 1) * AABB_FEATURES[1]
    directions = torch.nn.functional.normalize(positions + 0.1, dim=-1)
    with torch.no_grad():
        for _ in range(2):
            ours = field.inference_color(positions, directions, 0, wp)
            assert torch.equal(ours, field.color(positions, directions, 0))
    said = capsys.readouterr().out
    assert said.count("fused grid reads for (6, 3, 2) channels unavailable (RuntimeError: CPU kernel build") == 1


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
    difference = float((low - full).abs().max().detach())
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
    for max_baked in (None, 0):  # the baked features, then the planes read by the kernel (and the bfloat16 basis)
        if max_baked is not None:
            monkeypatch.setattr("frugalnerf_ns.field.radiance_field.BAKED_FEATURES_MAX_ENTRIES", max_baked)
        assert (model.field.baked_features(0) is None) == (max_baked == 0)
        ours, reference = render(model.field, 0, wp, origins, directions), render(model.field, 0, None, origins, directions)
        largest = float((ours.rgb - reference.rgb).abs().max())
        psnr = -10 * torch.log10(((ours.rgb - reference.rgb) ** 2).mean())
        assert 0 < largest < 1 / 255 and float(psnr) > 50, (largest, float(psnr))


def test_jobs_on_every_core_run_in_the_pool_and_come_back_in_order(monkeypatch):
    import threading

    jobs = [(lambda k=k: (k, threading.current_thread().name)) for k in range(7)]
    monkeypatch.setitem(fused_kernels._state, "pool", (None, 0, 0))  # a pool of this test's own, dropped after it
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    results = fused_kernels.on_every_core(jobs)
    assert [k for k, _ in results] == list(range(7))
    assert all(name.startswith("frugalnerf-fused") for _, name in results)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 1)  # one core: in this thread, no pool
    assert {name for _, name in fused_kernels.on_every_core(jobs)} == {threading.current_thread().name}
    with pytest.raises(ZeroDivisionError):  # a job's error reaches the caller
        fused_kernels.on_every_core([lambda: 1, lambda: 1 / 0])


@pytest.mark.skipif(torch.get_num_threads() < 2, reason="one core: no pool")
def test_torch_in_the_pool_runs_on_one_thread_and_the_caller_keeps_its_threads(monkeypatch):
    # A pool thread leading OpenMP teams of its own would slow every later parallel torch operation of the caller.
    monkeypatch.setitem(fused_kernels._state, "pool", (None, 0, 0))
    threads = torch.get_num_threads()
    seen = fused_kernels.on_every_core([torch.get_num_threads] * 4)
    assert seen == [1] * 4 and torch.get_num_threads() == threads


@needs_warp
@pytest.mark.parametrize("threads", [1, 2])
def test_a_march_in_blocks_on_every_core_and_colours_in_parts_give_one_launchs_pixels(threads, monkeypatch):
    from frugalnerf_ns.model import rendering

    field = opaque_field(mask=True)
    origins, directions = rays(3000, seed=11)
    whole = render(field, 0, wp, origins, directions)
    calls = []
    march = fused_kernels.density_march
    monkeypatch.setattr(fused_kernels, "density_march", lambda *a: calls.append(a[4].shape[0]) or march(*a))
    monkeypatch.setitem(fused_kernels._state, "pool", (None, 0, 0))  # not left for later tests: torch's count is faked
    monkeypatch.setattr(torch, "get_num_threads", lambda: threads)
    monkeypatch.setattr(fused_kernels, "MARCH_BLOCK_RAYS", 256)
    monkeypatch.setattr(fused_kernels, "SPLIT_MIN_ROWS", 100)
    monkeypatch.setattr(rendering, "SHADE_ROWS", 500)
    parts = render(field, 0, wp, origins, directions)
    hits = int(intersect_aabb(origins, directions, field.aabb, 0.0).hit.sum())
    assert calls == [256] * (hits // 256) + ([hits % 256] if hits % 256 else []) and len(calls) > 4
    assert torch.equal(parts.accumulation, whole.accumulation) and torch.equal(parts.depth, whole.depth)
    assert torch.allclose(parts.rgb, whole.rgb, atol=1e-6)  # the colour MLP on other row counts: rounding at most
    close(parts, render(field, 0, None, origins, directions))


@needs_warp
def test_the_colour_parts_come_in_few_row_counts_and_give_the_unpadded_pixels(monkeypatch):
    from frugalnerf_ns.model import rendering

    field = opaque_field(mask=True)
    origins, directions = rays(3000, seed=11)
    monkeypatch.setattr(rendering, "SHADE_ROWS", 1000)
    monkeypatch.setattr(rendering, "SHADE_ROW_STEP", 1)  # no padding: the reference
    unpadded = render(field, 0, wp, origins, directions)
    monkeypatch.setattr(rendering, "SHADE_ROW_STEP", 96)
    counts = []
    shade = FrugalNeRFField.inference_color
    monkeypatch.setattr(FrugalNeRFField, "inference_color",
                        lambda self, p, *a, **k: counts.append(p.shape[0]) or shade(self, p, *a, **k))
    padded = render(field, 0, wp, origins, directions)
    assert len(counts) > 2 and all(c == 1000 for c in counts[:-1]) and counts[-1] % 96 == 0
    assert counts[-1] != 1000  # a last part of its own, padded (this scene's shaded samples are not a round number)
    assert torch.equal(padded.accumulation, unpadded.accumulation) and torch.equal(padded.depth, unpadded.depth)
    assert torch.allclose(padded.rgb, unpadded.rgb, atol=1e-6) and float(padded.rgb.std()) > 0.01


@needs_warp
def test_feature_reads_and_the_outer_space_split_over_the_cores_equal_one_launch(monkeypatch):
    from frugalnerf_ns.field.outer_space import OuterSpace

    torch.manual_seed(12)
    field = FrugalNeRFField(AABB_FEATURES, (21, 26, 19), density_components=(2, 2, 2), appearance_components=(5, 3, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch")
    outer = OuterSpace(torch.tensor([[-1.0, -0.5, -1.0], [1.0, 0.5, 1.0]]), 24, 4, 4, 32, 16)
    with torch.no_grad():
        for tensor in [*field.appearance_grid.planes, *field.appearance_grid.lines, *outer.density_grid.planes,
                       *outer.density_grid.lines, *outer.appearance_grid.planes, *outer.appearance_grid.lines]:
            tensor.uniform_(0.0, 0.8)
    coords = torch.rand(5001, 3, generator=torch.Generator().manual_seed(13)) * 2.2 - 1.1
    origins, directions = rays(999, seed=14)
    monkeypatch.setitem(fused_kernels._state, "pool", (None, 0, 0))
    monkeypatch.setattr(torch, "get_num_threads", lambda: 2)
    with torch.no_grad():
        tables = fused_kernels.channels_last(*field.appearance_grid.scale_views(1))
        monkeypatch.setattr(fused_kernels, "SPLIT_MIN_ROWS", 10**9)  # one launch
        one = fused_kernels.vm_features(wp, tables, coords), outer.render(origins, directions, False, 0.0, wp)
        monkeypatch.setattr(fused_kernels, "SPLIT_MIN_ROWS", 100)  # a part per core
        split = fused_kernels.vm_features(wp, tables, coords), outer.render(origins, directions, False, 0.0, wp)
    assert torch.equal(one[0], split[0]) and float(one[0].abs().mean()) > 0.05
    for a, b in zip(one[1], split[1]):  # front, behind
        assert torch.equal(a.rgb, b.rgb) and torch.equal(a.accumulation, b.accumulation) and torch.equal(a.depth, b.depth)
    assert float(one[1][1].accumulation.mean()) > 0.05


@needs_warp
def test_with_the_kernels_the_model_renders_a_frame_in_one_chunk_and_keeps_its_chunk_option():
    from nerfstudio.cameras.cameras import Cameras

    from tests.helpers import tiny_model

    model = tiny_model(eval_num_rays_per_chunk=100)
    model.eval()
    with torch.no_grad():
        for line in model.field.density_grid.lines:
            line.add_(0.4)
    camera = Cameras(camera_to_worlds=torch.tensor([[[1.0, 0.0, 0.0, 0.1], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 2.5]]]),
                     fx=30.0, fy=30.0, cx=16.0, cy=12.0, width=32, height=24)
    chunks = []
    forward = model.forward
    model.forward = lambda ray_bundle: chunks.append(len(ray_bundle)) or forward(ray_bundle=ray_bundle)
    frames = {}
    for kernels in ("warp", "torch"):
        model.config.kernels = kernels
        chunks.clear()
        frames[kernels] = model.get_outputs_for_camera(camera)
        assert chunks == ([32 * 24] if kernels == "warp" else [100] * 7 + [68])
        assert model.config.eval_num_rays_per_chunk == 100
    assert frames["warp"]["rgb"].shape == (24, 32, 3) and float(frames["torch"]["accumulation"].max()) > 0.5
    assert torch.allclose(frames["warp"]["rgb"], frames["torch"]["rgb"], atol=2e-5)
    # A column of selected rays (the masked evaluator's call: offline_tools.render_view) in one chunk too.
    model.config.kernels = "warp"
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    inside = frames["torch"]["accumulation"][..., 0] > 0.5
    count = int(inside.sum())
    chunks.clear()
    column = model.get_outputs_for_camera_ray_bundle(bundle[inside].reshape((count, 1)))["rgb"]
    assert chunks == [count] and column.shape == (count, 1, 3) and 100 < count < 32 * 24
    assert torch.allclose(column[:, 0], frames["torch"]["rgb"][inside], atol=2e-5)
    model.train()  # training renders through nerfstudio's chunks whatever the kernels
    chunks.clear()
    with torch.no_grad():
        model.get_outputs_for_camera_ray_bundle(camera.generate_rays(camera_indices=0, keep_shape=True))
    assert chunks == [100] * 7 + [68]


def test_the_fused_linear_relu_gives_relu_of_the_linear():
    from frugalnerf_ns.field.color_mlp import linear_relu

    generator = torch.Generator().manual_seed(15)
    x, weight, bias = torch.randn(3000, 27, generator=generator), torch.randn(64, 27, generator=generator), torch.randn(64, generator=generator)
    for dtype in (torch.float32, torch.bfloat16):
        ours = linear_relu(x.to(dtype), weight.to(dtype), bias.to(dtype))
        reference = torch.relu(torch.nn.functional.linear(x.to(dtype), weight.to(dtype), bias.to(dtype)))
        assert ours.dtype == dtype and torch.allclose(ours.float(), reference.float(), rtol=1e-2, atol=1e-2)
        assert float((ours == 0).float().mean()) > 0.3 and float(ours.min()) == 0.0


@pytest.mark.skipif(torch.get_num_threads() < 2 or not hasattr(__import__("os"), "fork"), reason="no pool / no fork")
def test_a_forked_child_gets_a_pool_of_its_own():
    import os

    fused_kernels.on_every_core([lambda: 1, lambda: 2])  # the parent's pool exists
    child = os.fork()
    if child == 0:  # the parent's pool threads are not in the child: a job sent to them would never run
        import signal

        signal.alarm(30)  # a child that hangs dies instead (and fails the test)
        code = 0 if fused_kernels.on_every_core([lambda: 1, lambda: 2]) == [1, 2] else 1
        os._exit(code)
    _, status = os.waitpid(child, 0)
    assert os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0


@needs_warp
def test_the_render_bench_runs_an_earlier_trees_kernels_where_their_arguments_match(tmp_path):
    from pathlib import Path

    from frugalnerf_ns.bench.render import _kernels_of_tree

    source = Path(fused_kernels.__file__).with_name("fused_kernel_source.py")
    own = _kernels_of_tree(source, wp)
    assert set(own) == {"density_march", "outer_composite"}
    assert all(own[name] is not wp.kernels[name] for name in own)  # compiled from that file, not this tree's
    # A tree whose march takes another argument: this tree's launch could not feed it, so it keeps this tree's march.
    changed = tmp_path / "fused_kernel_source.py"
    text = source.read_text()
    marker = "stop_optical: wp.float32, max_optical: wp.float32,"
    assert marker in text
    changed.write_text(text.replace(marker, marker + " unused: wp.float32,", 1))
    assert set(_kernels_of_tree(changed, wp)) == {"outer_composite"}
