"""Optional monocular depth prior (paper Eq. 11, L_d; off by default: FrugalNeRF needs no learned prior).

A ``transformers`` depth-estimation checkpoint (DPT, Depth-Anything, ...) that the user has on disk is run
once on the training images; its predictions are cached next to the data. Nothing is ever downloaded:
the model loads with ``local_files_only``. The loss compares rendered and predicted depth by Pearson
correlation, which ignores the prediction's unknown scale and shift.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Optional, Sequence

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.cache import load_keyed_arrays, save_keyed_arrays
from frugalnerf_ns.data.input_checks import DataError

OPTION = "--pipeline.datamanager.mono-depth-model"


def _transformers():
    try:
        import transformers
    except ImportError as err:
        raise DataError(
            f"{OPTION} needs the transformers package: pip install 'frugalnerf-ns[mono]' (or transformers)"
        ) from err
    return transformers


def load_depth_model(path: Path):
    """The depth-estimation model saved at ``path`` (a folder with config.json and weights), never a download."""
    path = Path(path)
    if not path.exists():
        raise DataError(f"{OPTION} {path}: no such folder (save a transformers depth model there first)")
    if not (path / "config.json").exists():
        raise DataError(f"{OPTION} {path}: not a transformers model folder (no config.json)")
    transformers = _transformers()
    try:
        model = transformers.AutoModelForDepthEstimation.from_pretrained(str(path), local_files_only=True)
    except Exception as err:  # noqa: BLE001 - any loading failure is the user's folder, said plainly
        raise DataError(f"{OPTION} {path}: could not load a depth-estimation model ({type(err).__name__}: {err})") from err
    return model.eval()


@torch.no_grad()
def predict_depth(model, images: Float[Tensor, "views height width 3"], input_size: int = 384) -> Float[Tensor, "views height width"]:
    """Run ``model`` on each image (resized to ``input_size``^2, normalised to [-1, 1] as DPT expects) and
    resize the prediction back to the image size."""
    predictions = []
    for image in images:
        x = image.permute(2, 0, 1)[None].float()
        x = torch.nn.functional.interpolate(x, size=(input_size, input_size), mode="bilinear", align_corners=False)
        out = model(pixel_values=(x - 0.5) / 0.5).predicted_depth
        out = out.reshape(1, 1, *out.shape[-2:])
        out = torch.nn.functional.interpolate(out, size=image.shape[:2], mode="bilinear", align_corners=False)
        predictions.append(out[0, 0])
    return torch.stack(predictions)


def mono_depth_key(model_path: Path, images: Sequence[np.ndarray], disparity: bool, input_size: int) -> str:
    """Hash of the model folder (names, sizes, times), the settings and the images' pixels."""
    digest = hashlib.sha256()
    digest.update(str(Path(model_path).resolve()).encode())
    digest.update(f"{disparity} {input_size}".encode())
    for name in sorted(Path(model_path).glob("*")):
        if name.is_file():
            digest.update(name.name.encode())
            digest.update(str(name.stat().st_size).encode() + str(name.stat().st_mtime_ns).encode())
    for image in images:
        digest.update(np.ascontiguousarray(image).tobytes())
    return digest.hexdigest()


def load_or_predict(
    model_path: Path,
    images: Float[Tensor, "views height width 3"],
    cache: Optional[Path],
    disparity: bool,
    input_size: int = 384,
) -> Float[Tensor, "views height width"]:
    """Predicted depth of the training images, from ``cache`` when it was made by the same model on the same
    images; disparity predictions (DPT, Depth-Anything) are turned into depth-like values by negation, which
    keeps Pearson correlation meaningful without dividing by near-zero disparities."""
    arrays = [np.round(image.cpu().numpy() * 255).astype(np.uint8) for image in images]
    key = mono_depth_key(model_path, arrays, disparity, input_size)
    if cache is not None:
        cached, _ = load_keyed_arrays(cache, key)  # missing, stale or unreadable: predict again
        if cached is not None and cached.get("depth", np.empty(0)).shape == tuple(images.shape[:3]):
            return torch.from_numpy(cached["depth"]).float()
    depth = predict_depth(load_depth_model(model_path), images.cpu(), input_size)
    if disparity:
        depth = -depth
    if cache is not None:
        try:
            save_keyed_arrays(cache, key, depth=depth.numpy())
        except OSError:
            pass  # a read-only data folder: predictions stay in memory
    return depth
