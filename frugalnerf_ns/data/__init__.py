"""Floor 2, beside the model, data: the dataparsers of every layout we read (``dataparsers/``) behind one-line input checks
(``input_checks``); the dataset and the datamanager that builds each step's typed batch: training patches,
sparse-depth rays and novel-view rays (``dataset``, ``datamanager``, ``patches``, ``novel_cameras``); what is
derived once from the training views (``training_views``); sparse depth from pycolmap (``sparse_points``) as a run gets it, cached (``training_points``),
whether the cameras explain the photos (``camera_check``), near and far from those points where poses carry none (``scene_bounds``),
cameras of photos without poses (``photo_poses``, its pycolmap steps in ``photo_geometry``), images downscaled once into the cache (``downscaled_images``),
COLMAP's ``points3D.bin`` read without pycolmap (``colmap_points``), optional monocular depth (``mono_depth``),
few-shot splits (``splits``) and the embedded procedural scene (``procedural_scene``). Imports the floors below
(the batch types in the package root among them), never the model, tools or run.
"""

from typing import Any


def __getattr__(name: str) -> Any:
    # Runs trained before the package had rooms on nerfstudio-format data name
    # ``frugalnerf_ns.data.FrugalNerfstudioDataParserConfig`` in config.yml (this folder was then data.py).
    if name in ("FrugalNerfstudioDataParserConfig", "CheckedNerfstudio", "DataError"):
        from frugalnerf_ns.data import input_checks

        return getattr(input_checks, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
