"""Render time of a trained FrugalNeRF run, the training marcher beside the inference marcher, in one process.

  frugalnerf-bench render <run>/config.yml [--frames 4] [--views 3] [--out outputs/benchmark_render.json]

Rows (seconds per frame or per test view, same machine, same model, same image size, full scale):
- test view, training marcher (before issue 31): ``render_scale``, every sample slot of every ray
  (``--pipeline.model.fast-inference False``);
- test view, inference marcher (now): ``render_scale_inference``, blocks of slots, rays dropped once they
  leave the box or turn opaque; with the PSNR and largest pixel difference between the two renders;
- test view and spiral frame, inference marcher on its torch path and with the fused kernels
  (``--pipeline.model.kernels torch`` / ``warp``; where the CPU multiplies bfloat16 also the kernels with the
  float32 colour MLP, and the kernels on one core in chunks of ``eval_num_rays_per_chunk``, as before they used
  every core), alternating over ``--repeats`` rounds (medians), with the PSNR and largest pixel
  difference between them (when Warp compiles here);
- with ``--before DIR`` (a source tree of an earlier commit, e.g. ``git worktree add /tmp/before <rev>``): test
  view, that tree's ``render_scale_inference`` run on this process's model (it must call only field methods
  this tree still has), timed alternately with this tree's over ``--repeats`` rounds (medians);
- spiral frame, now: the scene's video path (``video.scene_video_cameras``), what ``ns-render spiral`` renders;
- ns-eval per test view, now: nerfstudio's ``get_average_eval_image_metrics`` calls for a subset of views;
- offline evaluator per test view: ``offline_tools.score_test_view``, what ``offline_tools eval`` runs per view.
Prints a Markdown table and writes JSON.
"""

from __future__ import annotations

import argparse
import importlib.util
import inspect
import statistics
import sys
import time
from pathlib import Path

from frugalnerf_ns.config_files import outputs_dir
from frugalnerf_ns.bench.report import markdown_table, write_report


def timed(fn) -> float:
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def main(argv=None) -> list:
    parser = argparse.ArgumentParser(prog="frugalnerf-bench render", description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", type=Path, help="config.yml of a trained FrugalNeRF run")
    parser.add_argument("--frames", type=int, default=4, help="spiral frames timed per row")
    parser.add_argument("--views", type=int, default=3, help="test views timed per evaluation row (at most all)")
    parser.add_argument("--out", type=Path, default=outputs_dir("benchmark_render.json"))
    parser.add_argument("--before", type=Path, help="source tree of an earlier commit: time its inference marcher too")
    parser.add_argument("--repeats", type=int, default=3, help="alternating rounds of the --before comparison")
    args = parser.parse_args(argv)
    if not args.config.is_file():
        sys.exit(f"benchmark_render: error: {args.config} is not a file (pass <run>/config.yml)")
    before_marcher = marcher_from_tree(args.before) if args.before else None

    import torch
    from nerfstudio.utils.eval_utils import eval_setup
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools.offline_tools import score_test_view
    from frugalnerf_ns.field.fused_kernels import warp_kernels
    from frugalnerf_ns.tools.video import scene_video_cameras

    _, pipeline, _, _ = eval_setup(args.config, test_mode="test")
    pipeline.eval()
    model, datamanager = pipeline.model, pipeline.datamanager
    start = datamanager.eval_dataset.cameras[0:1]
    size = f"{int(start.width)}x{int(start.height)}"
    dataset = datamanager.eval_dataset
    views = list(range(min(args.views, len(dataset))))

    def render_path(cameras):
        with torch.no_grad():
            for i in range(len(cameras)):
                model.get_outputs_for_camera(cameras[i : i + 1].to(model.device))

    def ns_eval():
        # get_average_eval_image_metrics scores the whole eval set; time a subset through the same calls.
        with torch.no_grad():
            for index in views:
                camera = dataset.cameras[index : index + 1].to(model.device)
                outputs = model.get_outputs_for_camera(camera)
                batch = dataset[index]
                model.get_image_metrics_and_images(outputs, batch)

    lpips = OfflineLPIPS().to(pipeline.device)

    def offline():
        for index in views:
            score_test_view(pipeline, dataset, index, lpips)

    renders = {}

    def test_views(fast: bool, key=None):
        model.config.fast_inference = fast
        with torch.no_grad():
            renders[fast if key is None else key] = [
                model.get_outputs_for_camera(dataset.cameras[i : i + 1].to(model.device))["rgb"] for i in views]

    def compare_before() -> list:
        """This tree's inference marcher and the --before tree's, alternating, median seconds per test view."""
        import frugalnerf_ns.model.frugalnerf as model_module

        now_marcher, times = model_module.render_scale_inference, {"before": [], "now": []}
        try:
            for _ in range(args.repeats):
                for key, marcher in (("before", before_marcher), ("now", now_marcher)):
                    model_module.render_scale_inference = marcher
                    times[key].append(timed(lambda: test_views(True, key)) / len(views))
        finally:
            model_module.render_scale_inference = now_marcher
        return [(f"test view, inference marcher of {args.before} (before), median of {args.repeats}",
                 statistics.median(times["before"])),
                (f"test view, inference marcher (now), median of {args.repeats}", statistics.median(times["now"]))]

    def compare_kernels() -> list:
        """The inference marcher on its torch path and with the fused kernels, alternating, median seconds per test
        view and per spiral frame."""
        from frugalnerf_ns.field import fused_kernels, radiance_field
        import frugalnerf_ns.model.frugalnerf as model_module

        chosen, native, times = model.config.kernels, radiance_field.native_bfloat16, {}
        every_core, chunk_rays = fused_kernels.on_every_core, model_module.FUSED_CHUNK_RAYS
        # Where the CPU multiplies bfloat16, "warp" (the default) shades in bfloat16: its float32 colour beside it.
        # "warp one core": the kernels as before they used every core (the model's eval_num_rays_per_chunk, each
        # launch in this thread).
        paths = ("torch", "warp float32 colour", "warp one core", "warp") if native() else ("torch", "warp one core", "warp")
        try:
            for _ in range(args.repeats):
                for path in paths:
                    model.config.kernels = path.split()[0]
                    radiance_field.native_bfloat16 = native if path.startswith("warp") and "float32" not in path \
                        else (lambda: False)
                    one_core = path == "warp one core"
                    fused_kernels.on_every_core = (lambda jobs: [job() for job in jobs]) if one_core else every_core
                    model_module.FUSED_CHUNK_RAYS = 0 if one_core else chunk_rays
                    times.setdefault(("view", path), []).append(timed(lambda: test_views(True, path)) / len(views))
                    times.setdefault(("frame", path), []).append(timed(lambda: render_path(ours)) / args.frames)
        finally:
            model.config.kernels, radiance_field.native_bfloat16 = chosen, native
            fused_kernels.on_every_core, model_module.FUSED_CHUNK_RAYS = every_core, chunk_rays
        named = {"torch": "torch path", "warp float32 colour": "fused kernels, float32 colour MLP",
                 "warp one core": "fused kernels on one core in chunks of eval_num_rays_per_chunk (before)",
                 "warp": "fused kernels" + (", bfloat16 colour MLP (the default here)" if native() else "")}
        return [(f"{what}, inference marcher, {named[path]}, median of {args.repeats}", statistics.median(times[(key, path)]))
                for key, what in (("view", "test view"), ("frame", "spiral frame")) for path in paths]

    model.num_rendered_scales = None  # the default outside the viewer: the full scale only
    ours = scene_video_cameras(datamanager, start, args.frames)
    ns_eval()  # warm-up: LPIPS weights, first-call allocations
    kernel_rows = compare_kernels() if warp_kernels("auto") is not None else []
    rows = [
        *kernel_rows,
        ("test view, training marcher (before)", timed(lambda: test_views(False)) / len(views)),
        ("test view, inference marcher (now)", timed(lambda: test_views(True)) / len(views)),
        ("spiral frame, now (scene path)", timed(lambda: render_path(ours)) / args.frames),
        ("ns-eval per test view, now", timed(ns_eval) / len(views)),
        ("offline evaluator per test view", timed(offline) / len(views)),
    ]
    agreement = {"psnr_inference_vs_training_marcher": psnr_between(renders[True], renders[False]),
                 "max_pixel_difference": largest_difference(renders[True], renders[False])}
    if kernel_rows:
        agreement["psnr_warp_vs_torch"] = psnr_between(renders["warp"], renders["torch"])
        agreement["max_pixel_difference_warp_vs_torch"] = largest_difference(renders["warp"], renders["torch"])
        agreement["max_pixel_difference_warp_vs_one_core"] = largest_difference(renders["warp"], renders["warp one core"])
        if "warp float32 colour" in renders:
            agreement["psnr_warp_float32_vs_torch"] = psnr_between(renders["warp float32 colour"], renders["torch"])
    if before_marcher is not None:
        rows += compare_before()
        agreement["psnr_inference_vs_before"] = psnr_between(renders["now"], renders["before"])
    model.num_rendered_scales = None
    records = [{"run": str(args.config.parent), "row": name, "seconds": seconds, "image": size,
                "threads": torch.get_num_threads(), "device": str(pipeline.device), **agreement}
               for name, seconds in rows]
    heading = f"{args.config.parent} ({size}, {torch.get_num_threads()} threads)"
    table = markdown_table(records, [(heading, lambda r: r["row"]), ("seconds", lambda r: f"{r['seconds']:.2f}")])
    table += (f"\n\ninference vs training marcher on {len(views)} test views: PSNR "
              f"{agreement['psnr_inference_vs_training_marcher']:.1f} dB, largest pixel difference "
              f"{agreement['max_pixel_difference']:.2e}")
    if kernel_rows:
        table += (f"\nfused kernels vs torch path on {len(views)} test views: PSNR {agreement['psnr_warp_vs_torch']:.1f} dB, "
                  f"largest pixel difference {agreement['max_pixel_difference_warp_vs_torch']:.2e}")
        if "psnr_warp_float32_vs_torch" in agreement:
            table += f" (with the float32 colour MLP: PSNR {agreement['psnr_warp_float32_vs_torch']:.1f} dB)"
        table += (f"\nfused kernels on every core vs one core: largest pixel difference "
                  f"{agreement['max_pixel_difference_warp_vs_one_core']:.2e}")
    if before_marcher is not None:
        table += (f"\ninference marcher now vs {args.before}: PSNR {agreement['psnr_inference_vs_before']:.1f} dB, "
                  f"largest pixel difference {largest_difference(renders['now'], renders['before']):.2e}")
    write_report("benchmark_render", table, records, args.out)
    return records


def psnr_between(first: list, second: list) -> float:
    import torch

    difference = torch.cat([(a - b).flatten() for a, b in zip(first, second)])
    return float(-10 * torch.log10((difference**2).mean().clamp_min(1e-20)))


def largest_difference(first: list, second: list) -> float:
    return max(float((a - b).abs().max()) for a, b in zip(first, second))


def _load_private(path: Path, name: str):
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the file runs
    spec.loader.exec_module(module)  # type: ignore[union-attr]
    return module


def _with_kernels_of_tree(marcher, tree: Path):
    """``marcher`` handed that tree's own ``define_kernels`` kernels (the density march, the space beyond a box) in
    place of this tree's, each where its arguments are the same (this tree launches them); else this tree's."""
    source = tree / "frugalnerf_ns" / "field" / "fused_kernel_source.py"
    cache: dict = {}

    def with_own(*args, kernels=None, **kwargs):
        if kernels is not None and source.is_file():
            if "own" not in cache:
                cache["own"] = _kernels_of_tree(source, kernels)
            kernels = type(kernels)(kernels.wp, {**kernels.kernels, **cache["own"]})
        return marcher(*args, kernels=kernels, **kwargs)

    return with_own


def _kernels_of_tree(source: Path, kernels) -> dict:
    """The kernels ``define_kernels`` of ``source`` builds, compiled for the CPU, that take the arguments this tree's
    kernels of the same name take."""
    built = _load_private(source, "frugalnerf_before_kernel_source").define_kernels(kernels.wp)
    kernels.wp.load_module(built["module"], device="cpu")

    def arguments(kernel) -> list:
        return [argument.label for argument in kernel.adj.args]

    return {name: kernel for name, kernel in built.items() if name != "module" and name in kernels.kernels
            and arguments(kernel) == arguments(kernels.kernels[name])}


def marcher_from_tree(tree: Path):
    """``render_scale_inference`` of another source tree's ``frugalnerf_ns/model/rendering.py``, loaded under a
    private module name beside this tree's package (whose other modules it imports). Methods of
    ``BakedDensity`` that the earlier marcher calls and this tree no longer has are lent from that tree's
    ``radiance_field.py`` (they read only the fields both trees' ``BakedDensity`` hold)."""
    path = tree / "frugalnerf_ns" / "model" / "rendering.py"
    if not path.is_file():
        sys.exit(f"benchmark_render: error: --before {tree}: no {path} (pass a source tree, e.g. a git worktree)")
    field_path = tree / "frugalnerf_ns" / "field" / "radiance_field.py"
    before_field = None
    if field_path.is_file():
        from frugalnerf_ns.field import radiance_field

        try:
            before_field = _load_private(field_path, "frugalnerf_before_radiance_field")
        except ImportError:  # it imports a module this tree has renamed (a recent tree): no methods lent
            sys.modules.pop("frugalnerf_before_radiance_field", None)
    if before_field is not None:
        for name, member in vars(before_field.BakedDensity).items():
            if callable(member) and not name.startswith("__") and not hasattr(radiance_field.BakedDensity, name):
                setattr(radiance_field.BakedDensity, name, member)
    marcher = _load_private(path, "frugalnerf_before_rendering").render_scale_inference
    if "kernels" in inspect.signature(marcher).parameters:
        return _with_kernels_of_tree(marcher, tree)

    def without_kernels(*args, kernels=None, **kwargs):  # a tree from before the fused kernels: its torch path
        return marcher(*args, **kwargs)

    return without_kernels
