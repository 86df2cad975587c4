"""Floor 3, tools built on a trained model: the offline evaluator behind ``ns-eval``-style scoring
(``offline_tools``), ``make demo`` (``demo``), video cameras for ``ns-render`` (``video``), where to take the next
photo (``next_view``), and the sweep runner and quality gate (``sweep/``). Imports every floor below (data, model,
geometry, field, scoring, root), never run.
"""
