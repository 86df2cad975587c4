"""Floor 4, tools built on a trained model: the offline evaluator behind ``ns-eval``-style scoring
(``offline_tools``), ``make demo`` (``demo``), video cameras for ``ns-render`` (``video``) and a private ffmpeg
(``ffmpeg_path``), and the sweep runner and quality gate (``sweep/``). Imports every floor below (data, model,
geometry, field, scoring, root), never run.
"""
