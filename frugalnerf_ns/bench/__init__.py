"""Floor 5, measuring: ``frugalnerf-bench <subcommand>``, the one console tool for development measurements
(``cli``). Each subcommand is one module: scene benchmarks and the speed-accuracy trade-off, both through the
sweep runner (``scenes``, ``tradeoff``), FrugalNeRF against nerfstudio's tensorf (``vs_tensorf``), rendering,
viewer and start-up times (``render``, ``viewer``, ``startup``), the next-view tool's time (``next_view``), cameras
of photos without poses against published ones (``photo_cameras``), model size (``model_size``), seconds per
training step beside an earlier tree (``step_time``), a profiled training step (``profile_step``) and the
end-to-end GPU check (``gpu_check``) with its fused-kernel comparison (``kernel_check``) and timing probes
(``device_probes``). They share one pipeline builder (``pipelines``: a preset set up on a scene, its grid at the
final size) and one table-and-JSON writer (``report``); ``sparse_fit`` summarises how a run's depth meets the
sparse points for the sparse-depth diagnostic. The top floor: it may import every room; nothing in the package
imports it.
"""
