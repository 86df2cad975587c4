"""Images at 1/factor size, made once from the full-size files into the scene's cache (``scene_cache_dir``):
Blender frames at the protocol's half size, and LLFF or COLMAP captures that come with full-size ``images/``
only (a phone's photos)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable, Optional, Sequence, Tuple

import numpy as np
from PIL import Image, ImageOps, UnidentifiedImageError

from frugalnerf_ns.cache import scene_cache_dir, write_atomically
from frugalnerf_ns.data.input_checks import DataError, check_image_file

CPU_LONG_SIDE = 640
"""Longest image side the downscale chosen for full-size photos aims at (the CPU presets train at 504-640 px)."""


def area_downscale(pixels: np.ndarray, factor: int) -> np.ndarray:
    """Mean of every factor x factor block, channel by channel with straight (not premultiplied) alpha, as
    the protocol's cv2.resize(INTER_AREA) does for an integer factor; rows and columns past the last whole
    block are dropped."""
    height, width = pixels.shape[0] // factor, pixels.shape[1] // factor
    blocks = pixels[: height * factor, : width * factor].astype(np.float64)
    blocks = blocks.reshape(height, factor, width, factor, -1).mean(axis=(1, 3))
    return np.clip(np.round(blocks), 0, 255).astype(np.uint8)


def factor_for_long_side(width: int, height: int, long_side: int = CPU_LONG_SIDE) -> int:
    """The smallest integer downscale that brings the longer side to ``long_side`` pixels or fewer."""
    return max(1, math.ceil(max(width, height) / long_side))


def photo_size_and_factor(photo: Path) -> Tuple[int, int, int]:
    """(width, height, ``factor_for_long_side``) of a full-size photo (one clear line if it is unreadable)."""
    check_image_file(photo, photo.name)
    with Image.open(photo) as img:
        width, height = img.size
    return width, height, factor_for_long_side(width, height)


def _target(
    path: Path, factor: int, data: Path, say: Callable[[str], None], base: Optional[Path] = None, upright: bool = False
) -> Path:
    """Where the copy goes: ``images_<factor>/`` (``images_<factor>_upright/``) in the cache, under the path
    relative to ``base`` (default ``data``)."""
    base = (base or data).resolve()
    relative = path.resolve().relative_to(base) if path.resolve().is_relative_to(base) else Path(path.name)
    return scene_cache_dir(data, say) / _folder(factor, upright) / relative.with_suffix(".png")


def _folder(factor: int, upright: bool) -> str:
    return f"images_{factor}_upright" if upright else f"images_{factor}"


def downscaled(
    path: Path, factor: int, data: Path, say: Callable[[str], None] = print, base: Optional[Path] = None,
    upright: bool = False,
) -> Path:
    """The image at 1/factor size (``area_downscale``), written once to ``images_<factor>/`` in the scene's
    cache (under its path relative to ``base``, default ``data``) and reused while it is newer than the
    original. ``upright``: turned as its EXIF orientation says first (photos without cameras; posed layouts'
    cameras refer to the stored pixels), in ``images_<factor>_upright/``."""
    target = _target(path, factor, data, say, base, upright)
    if target.is_file() and target.stat().st_mtime >= path.stat().st_mtime:
        return target
    try:
        with Image.open(path) as img:
            turned = ImageOps.exif_transpose(img) if upright else img
            pixels = np.asarray(turned.convert("RGBA" if img.mode in ("RGBA", "LA", "P") else "RGB"))
    except (UnidentifiedImageError, SyntaxError, OSError) as err:
        raise DataError(f"image file {path} is unreadable or corrupt ({err})") from None
    try:
        small = Image.fromarray(area_downscale(pixels, factor))
        write_atomically(target, lambda f: small.save(f, format="PNG"))
    except OSError as err:
        raise DataError(f"could not write the downscaled copy of {path} to {target} ({err})") from None
    return target


def downscaled_all(
    paths: Sequence[Path], factor: int, data: Path, say: Callable[[str], None] = print, base: Optional[Path] = None,
    upright: bool = False,
) -> list:
    """``downscaled`` for each path, with one progress line when some have to be made."""
    missing = sum(not _target(p, factor, data, say, base, upright).is_file() for p in paths)
    if missing:
        cache = scene_cache_dir(data, say) / _folder(factor, upright)
        say(f"frugalnerf: making {missing} image(s) at 1/{factor} size in {cache} (once)")
    return [downscaled(p, factor, data, say, base, upright) for p in paths]
