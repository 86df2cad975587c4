"""Floor 4, running a training: the presets ``ns-train`` lists (``presets``), option checks (``options``), the
pipeline that joins datamanager and model (``pipeline``), the trainer with its interrupt-safe saves
(``trainer``, ``stepping``) and checkpoint reading and writing (``checkpoints``). It may import every room
below; only the measurements (``bench``, floor 5) import it.
"""
