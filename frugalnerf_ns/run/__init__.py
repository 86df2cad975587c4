"""Floor 5, running a training: the presets ``ns-train`` lists (``presets``), option checks (``options``), the
pipeline that joins datamanager and model (``pipeline``), the trainer with its interrupt-safe saves
(``trainer``, ``stepping``) and checkpoint reading and writing (``checkpoints``, ``checkpoint_compat``). The top
floor: it may import every room; nothing in the package imports it except the package root's start-up hooks.
"""
