"""Floor 5, running a training: the presets ``ns-train`` lists (``presets``), option checks (``options``), the
pipeline that joins datamanager and model (``pipeline``), the trainer with its interrupt-safe saves
(``trainer``, ``stepping``) and checkpoint reading and writing (``checkpoints``, ``checkpoint_compat``). It may
import every room below; only the measurements (``bench``, floor 6) and the package root's start-up hooks import
it.
"""
