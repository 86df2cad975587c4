"""Floor 2, the model: FrugalNeRF as a nerfstudio ``Model`` (``frugalnerf``) and its settings (``config``);
rendering every scale of a ray bundle (``rendering``); the training objective and its terms (``objective``,
``losses``, ``geometric_adaptation``: the paper's equations, each in one named function); the schedule of
upsampling and alpha masks (``training_schedule``); test-view scoring (``image_scoring``). Imports the floors
below (the root with the batch types the datamanager hands in, geometry, field, scoring), never data (beside it on
floor 2), tools or run.
"""

from typing import Any


def __getattr__(name: str) -> Any:
    # Runs trained before the package had rooms name ``frugalnerf_ns.model.FrugalNeRFModel`` in config.yml
    # (this folder was then the module model.py); resolved on first use so that importing a sibling such as
    # ``frugalnerf_ns.model.losses`` does not load the whole model.
    if name in ("FrugalNeRFModel", "FrugalNeRFModelConfig"):
        from frugalnerf_ns.model import frugalnerf

        return getattr(frugalnerf, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
