"""The scene benchmark's config refers to registered methods/parsers; offline LPIPS stands in for torchmetrics'."""

from importlib.metadata import entry_points
from pathlib import Path

import torch
import yaml

from frugalnerf_ns.bench import scenes as bench

ROOT = Path(__file__).resolve().parents[1]


def test_scene_config_uses_registered_presets_and_parsers():
    config = yaml.safe_load((ROOT / "configs" / "benchmark_scenes.yaml").read_text())
    methods = {ep.name for ep in entry_points(group="nerfstudio.method_configs")}
    parsers = {ep.name for ep in entry_points(group="nerfstudio.dataparser_configs")}
    for name, scene in config["scenes"].items():
        assert scene["preset"] in methods, name
        assert scene["parser"][0] in parsers, name
        # The paper's 2- and 3-view settings; NeRF-synthetic's few-shot protocol (DietNeRF, FreeNeRF) is 8 views;
        # a capture of our own (captures/) has the splits its README names.
        if scene["data"].startswith("captures/"):
            assert scene["views"], name
        else:
            assert ({8} if scene["parser"][0] == "frugal-blender" else {2, 3}) <= set(scene["views"]), name
    assert set(config["baselines"]) >= {"tensorf", "nerfacto"}


def test_markdown_table_has_a_row_per_run_and_averages():
    runs = [
        {"scene": s, "method": m, "psnr": p, "ssim": 0.5, "lpips": 0.4, "train_seconds": 60.0, "checkpoint_mb": 10.0,
         "peak_rss_mib": 1000.0}
        for s, m, p in [("a", "frugal", 18.0), ("a", "tensorf", 16.0), ("b", "frugal", 20.0), ("b", "tensorf", 17.0)]
    ]
    table = bench.markdown(runs).splitlines()
    assert len(table) == 2 + 4 + 2
    assert table[-2].startswith("| average | frugal | 19.00 |") and table[-1].startswith("| average | tensorf | 16.50 |")
    assert "regnerf25" not in table[0]


def test_markdown_table_shows_the_shorter_test_list_beside_the_full_one():
    run = {"scene": "dtu", "method": "frugal", "psnr": 15.0, "ssim": 0.7, "lpips": 0.2, "regnerf25_psnr": 16.5,
           "regnerf25_ssim": 0.75, "regnerf25_lpips": 0.18, "train_seconds": 60.0, "checkpoint_mb": 1.0,
           "peak_rss_mib": 1.0}
    header, rule, row = bench.markdown([run]).splitlines()
    assert "PSNR / SSIM / LPIPS (regnerf25)" in header and header.count("|") == rule.count("|")
    assert "| 15.00 | 0.700 | 0.200 | 16.500 / 0.750 / 0.180 |" in row


def test_torchmetrics_lpips_is_replaced_by_the_offline_one():
    from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS
    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips
    from tests.lpips_fixture import fixed_image_pair

    patch_torchmetrics_lpips()
    from torchmetrics.image.lpip import LearnedPerceptualImagePatchSimilarity

    metric = LearnedPerceptualImagePatchSimilarity(normalize=True)  # would download AlexNet unpatched
    a, b = fixed_image_pair()
    assert torch.allclose(metric(a, b), OfflineLPIPS()(a, b).mean(), atol=1e-6)
    unnormalized = LearnedPerceptualImagePatchSimilarity()
    assert torch.allclose(unnormalized(a * 2 - 1, b * 2 - 1), metric(a, b), atol=1e-6)


def test_ablation_variants_name_real_options_of_the_presets():
    from frugalnerf_ns.run.presets import build_trainer_config

    config = yaml.safe_load((ROOT / "configs" / "benchmark_scenes.yaml").read_text())
    assert set(config["variants"]) >= {"no-geo", "no-novel", "single-scale"}
    trainer = build_trainer_config("frugalnerf-cpu")
    for name, args in config["variants"].items():
        options = args[0::2]
        for option in options:
            target = trainer
            *parents, leaf = option.lstrip("-").replace("-", "_").split(".")
            for part in parents:
                target = getattr(target, part)
            assert hasattr(target, leaf), (name, option)


def test_variant_runs_keep_the_registered_method_name_in_their_path(tmp_path):
    from frugalnerf_ns.tools.sweep.grid import expand
    from frugalnerf_ns.tools.sweep.runner import run_location

    config = ROOT / "configs" / "benchmark_scenes.yaml"
    full, no_geo, tensorf = expand(config, ["fern"], [2], ["frugalnerf-cpu", "tensorf"],
                                   {"full": [], "no-geo": ["--pipeline.model.geo-weight", "0"]}, [None])
    assert (full.label, no_geo.label, tensorf.label) == ("frugalnerf-cpu", "frugalnerf-cpu[no-geo]", "tensorf")
    # nerfstudio writes <output>/<experiment>/<method>/<timestamp>; the method part must be registered.
    experiment, run_dir = run_location(no_geo, tmp_path)
    assert experiment == "fern-2v" and run_dir == tmp_path / "runs" / "fern-2v" / "frugalnerf-cpu" / no_geo.key
    assert run_location(full, tmp_path)[1] != run_dir
    assert tensorf.parser_args[-2:] == ["--ndc", "False"] and "--ndc" not in full.parser_args


def test_markdown_table_with_seeds_adds_mean_and_spread_rows():
    runs = [
        {"scene": s, "method": "frugal", "seed": seed, "psnr": p, "ssim": 0.5, "lpips": 0.4, "train_seconds": 60.0,
         "checkpoint_mb": 10.0, "peak_rss_mib": 1.0}
        for s, seed, p in [("a", 1, 18.0), ("a", 2, 18.5), ("b", 1, 20.0), ("b", 2, 19.0)]
    ]
    table = bench.markdown(runs).splitlines()
    assert all(line.count("|") == table[0].count("|") for line in table)
    assert "| a | frugal | mean of 2 (spread) | 18.25 (0.50) |" in table[6]
    assert "| b | frugal | mean of 2 (spread) | 19.50 (1.00) |" in table[7]
    assert table[-1].startswith("| average | frugal | all | 18.88 |")
    from frugalnerf_ns.tools.sweep.grid import seed_args

    assert seed_args("frugalnerf-cpu", 3) == ["--machine.seed", "3", "--pipeline.datamanager.seed", "3"]
    assert seed_args("tensorf", 3) == ["--machine.seed", "3"] and seed_args("tensorf", None) == []
