"""A rendered scene for the camera-estimation tests: a textured wall behind a textured card (two depths, so views
are not related by one homography), pinhole cameras with an optional radial distortion, and the multi-scale
texture the SIFT tests share."""

import numpy as np
import torch
from PIL import Image, ImageFilter

from frugalnerf_ns.data.procedural_scene import look_at


def texture(size=512, seed=0):
    """Multi-scale random blobs about one texel per pixel: plenty of SIFT corners."""
    rng = np.random.default_rng(seed)
    tex = np.zeros((size, size), np.float32)
    for radius in (2, 4, 8):
        noise = Image.fromarray((rng.random((size, size)) * 255).astype(np.uint8)).filter(ImageFilter.GaussianBlur(radius))
        tex += np.asarray(noise, np.float32)
    tex -= tex.min()
    return tex / tex.max()


WIDTH, HEIGHT, FOCAL = 320, 240, 280.0


def camera(eye, target=(0.0, 0.0, -2.0)):
    return look_at(torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))[:3].double()


def render(c2w, seed=0, focal=FOCAL, radial=0.0):
    """A textured wall z = -3 + 0.2 y behind a textured card z = -1.6 - 0.15 x (x in [-0.7, 0.5], y in
    [-0.5, 0.6]): two depths, so the views are not related by one homography. ``radial``: COLMAP's
    SIMPLE_RADIAL k (a pixel at normalised distance r shows the ray at r / (1 + k r_u^2))."""
    v, u = torch.meshgrid(torch.arange(HEIGHT, dtype=torch.float64) + 0.5, torch.arange(WIDTH, dtype=torch.float64) + 0.5,
                          indexing="ij")
    x, y = (u - WIDTH / 2) / focal, (v - HEIGHT / 2) / focal
    xu, yu = x.clone(), y.clone()
    for _ in range(20):  # undistort: x = xu (1 + k (xu^2 + yu^2))
        factor = 1.0 + radial * (xu**2 + yu**2)
        xu, yu = x / factor, y / factor
    local = torch.stack([xu, -yu, -torch.ones_like(u)], -1)
    d = local @ c2w[:3, :3].T
    o = c2w[:3, 3]
    t_wall = (-3.0 - o[2] + 0.2 * o[1]) / (d[..., 2] - 0.2 * d[..., 1])
    t_card = (-1.6 - o[2] - 0.15 * o[0]) / (d[..., 2] + 0.15 * d[..., 0])
    card = o + d * t_card[..., None]
    on_card = (card[..., 0] > -0.7) & (card[..., 0] < 0.5) & (card[..., 1] > -0.5) & (card[..., 1] < 0.6) & (t_card > 0)
    hit = torch.where(on_card[..., None], card, o + d * t_wall[..., None])
    wall, front = texture(seed=seed), texture(seed=seed + 100)
    size = wall.shape[0]
    tx = ((hit[..., 0] + 3) / 6 * (size - 1)).clamp(0, size - 1).round().long().numpy()
    ty = ((hit[..., 1] + 3) / 6 * (size - 1)).clamp(0, size - 1).round().long().numpy()
    grey = np.where(on_card.numpy(), 0.3 + 0.7 * front[ty, tx], 0.7 * wall[ty, tx])
    return np.repeat((grey * 255).astype(np.uint8)[..., None], 3, axis=-1)


TRUE = [camera((-0.3, 0.05, 0.0)), camera((0.25, -0.05, 0.05)), camera((0.0, 0.25, -0.1)), camera((0.1, -0.2, 0.1))]


def write_photos(folder, cameras, suffix=".png", exif=None):
    """A photos-only folder: ``render`` of each camera saved as ``photo_<i><suffix>`` (with ``exif`` when given)."""
    folder.mkdir(parents=True, exist_ok=True)
    for i, c2w in enumerate(cameras):
        image = Image.fromarray(render(c2w))
        if exif is None:
            image.save(folder / f"photo_{i}{suffix}")
        else:
            image.save(folder / f"photo_{i}{suffix}", exif=exif)
    return folder
