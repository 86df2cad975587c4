"""Floor 6, measuring: ``frugalnerf-bench <subcommand>``, the one console tool for development measurements
(``cli``). Each subcommand is one module: scene benchmarks and the speed-accuracy trade-off, both through the
sweep runner (``scenes``, ``tradeoff``), FrugalNeRF against nerfstudio's tensorf (``vs_tensorf``), rendering,
viewer and start-up times (``render``, ``viewer``, ``startup``), model size (``model_size``), a profiled
training step (``profile_step``) and the end-to-end GPU check (``gpu_check``). They share one pipeline builder
(``pipelines``: a preset set up on a scene, its grid at the final size) and one table-and-JSON writer
(``report``). The top floor: it may import every room; nothing in the package imports it.
"""
