"""A small procedural scene with known cameras, written as a nerfstudio-format dataset.

It lets the demo and the tests train on any fresh machine without downloads: a striped sphere, a box and
a checkered ground disc, lit by one directional light, seen by cameras on an arc around it, rendered
exactly by ray casting (2x2 supersampled). Few training views, test views in between them.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Dict, List, Sequence, Tuple

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from frugalnerf_ns.geometry.camera_conventions import look_at_poses

WHITE = torch.ones(3)


@dataclass(frozen=True)
class SceneSpec:
    """Camera layout and image size of the procedural scene."""

    width: int = 96
    height: int = 72
    focal: float = 90.0
    radius: float = 2.6
    elevation_deg: float = 28.0
    azimuths_deg: Tuple[float, ...] = tuple(np.linspace(-40.0, 40.0, 9).tolist())
    train_ids: Tuple[int, ...] = (0, 4, 8)
    test_ids: Tuple[int, ...] = (2, 6)
    supersample: int = 2


def look_at(eye: Tensor, target: Tensor, world_up: Tensor = torch.tensor([0.0, 0.0, 1.0])) -> Tensor:
    """Camera-to-world (4x4, OpenGL axes as nerfstudio uses: x right, y up, looking down -z)."""
    c2w = torch.eye(4)
    c2w[:3] = look_at_poses(eye[None], target, world_up)[0]
    return c2w


def camera_poses(spec: SceneSpec) -> List[Tensor]:
    elev = math.radians(spec.elevation_deg)
    poses = []
    for az in spec.azimuths_deg:
        a = math.radians(az)
        eye = spec.radius * torch.tensor([math.cos(elev) * math.cos(a), math.cos(elev) * math.sin(a), math.sin(elev)])
        poses.append(look_at(eye, torch.tensor([0.0, 0.0, 0.25])))
    return poses


def _sphere_hit(o: Tensor, d: Tensor, center: Tensor, radius: float) -> Tensor:
    oc = o - center
    b = (oc * d).sum(-1)
    c = (oc * oc).sum(-1) - radius**2
    disc = b * b - c
    t = -b - torch.sqrt(disc.clamp_min(0))
    return torch.where((disc > 0) & (t > 1e-4), t, torch.full_like(t, math.inf))


def _box_hit(o: Tensor, d: Tensor, lo: Tensor, hi: Tensor) -> Tuple[Tensor, Tensor]:
    inv = 1.0 / torch.where(d.abs() < 1e-9, torch.full_like(d, 1e-9), d)
    t0, t1 = (lo - o) * inv, (hi - o) * inv
    tmin, tmax = torch.minimum(t0, t1), torch.maximum(t0, t1)
    t_enter, axis = tmin.max(dim=-1)
    t_exit = tmax.min(dim=-1).values
    hit = (t_exit > t_enter) & (t_enter > 1e-4)
    normal = torch.zeros_like(o)
    normal.scatter_(-1, axis[:, None], -torch.sign(d.gather(-1, axis[:, None])))
    return torch.where(hit, t_enter, torch.full_like(t_enter, math.inf)), normal


def shade_rays(origins: Tensor, directions: Tensor) -> Tensor:
    """Exact colour of each ray (N, 3) in [0, 1], on a white background."""
    return shade_rays_rgba(origins, directions)[:, :3]


def shade_rays_rgba(origins: Tensor, directions: Tensor) -> Tensor:
    """Colour (on white where nothing is hit) and coverage (1 where a surface is hit, else 0) of each ray."""
    light = torch.nn.functional.normalize(torch.tensor([0.4, -0.5, 1.0]), dim=0)
    n = origins.shape[0]
    colors = WHITE.expand(n, 3).clone()
    best = torch.full((n,), math.inf)

    # Ground disc z = 0, radius 1.1, checkered.
    t_plane = torch.where(directions[:, 2].abs() > 1e-9, -origins[:, 2] / directions[:, 2], torch.full((n,), math.inf))
    p = origins + directions * t_plane[:, None]
    on_disc = (t_plane > 1e-4) & (p[:, :2].norm(dim=-1) < 1.1)
    checker = ((torch.floor(p[:, 0] * 4) + torch.floor(p[:, 1] * 4)) % 2)[:, None]
    ground = torch.tensor([0.85, 0.75, 0.55]) * checker + torch.tensor([0.35, 0.45, 0.30]) * (1 - checker)
    ground = ground * (0.4 + 0.6 * light[2])
    take = on_disc & (t_plane < best)
    colors[take], best[take] = ground[take], t_plane[take]

    # Striped sphere.
    center, radius = torch.tensor([-0.15, 0.2, 0.4]), 0.4
    t_sph = _sphere_hit(origins, directions, center, radius)
    p = origins + directions * t_sph.clamp_max(1e6)[:, None]
    normal = (p - center) / radius
    stripes = (torch.floor((normal[:, 2] + 1.0) * 4) % 2)[:, None]
    albedo = torch.tensor([0.9, 0.2, 0.15]) * stripes + torch.tensor([0.95, 0.85, 0.2]) * (1 - stripes)
    lit = albedo * (0.3 + 0.7 * (normal @ light).clamp_min(0))[:, None]
    take = t_sph < best
    colors[take], best[take] = lit[take], t_sph[take]

    # Box with a face colour per axis.
    lo, hi = torch.tensor([0.15, -0.55, 0.0]), torch.tensor([0.55, -0.15, 0.5])
    t_box, normal = _box_hit(origins, directions, lo, hi)
    face = torch.tensor([[0.2, 0.35, 0.9], [0.2, 0.8, 0.4], [0.9, 0.9, 0.9]])[normal.abs().argmax(dim=-1)]
    lit = face * (0.3 + 0.7 * (normal @ light).clamp_min(0))[:, None]
    take = t_box < best
    colors[take], best[take] = lit[take], t_box[take]
    return torch.cat([colors.clamp(0, 1), torch.isfinite(best).float()[:, None]], dim=-1)


def render_view(c2w: Tensor, spec: SceneSpec, alpha: bool = False) -> Tensor:
    """(height, width, 3) on white, or with ``alpha`` (height, width, 4): straight colour and coverage."""
    s = spec.supersample
    v, u = torch.meshgrid(
        (torch.arange(spec.height * s) + 0.5) / s, (torch.arange(spec.width * s) + 0.5) / s, indexing="ij"
    )
    dirs_cam = torch.stack(
        [(u - spec.width / 2) / spec.focal, -(v - spec.height / 2) / spec.focal, -torch.ones_like(u)], dim=-1
    )
    dirs = torch.nn.functional.normalize(dirs_cam.reshape(-1, 3) @ c2w[:3, :3].T, dim=-1)
    origins = c2w[:3, 3].expand_as(dirs)
    rgba = shade_rays_rgba(origins, dirs).reshape(spec.height, s, spec.width, s, 4)
    if not alpha:
        return rgba[..., :3].mean(dim=(1, 3))
    coverage = rgba[..., 3:]
    covered = coverage.mean(dim=(1, 3))
    # Straight alpha: the mean colour of the covered sub-samples (so compositing on white gives back the
    # white-background render exactly).
    color = (rgba[..., :3] * coverage).mean(dim=(1, 3)) / covered.clamp_min(1e-6)
    return torch.cat([color * (covered > 0), covered], dim=-1)


def write_procedural_scene(out_dir: Path, spec: SceneSpec = SceneSpec()) -> Path:
    """Render every view and write ``images/`` plus ``transforms.json`` with train/val/test filenames."""
    out_dir = Path(out_dir)
    (out_dir / "images").mkdir(parents=True, exist_ok=True)
    frames: List[Dict] = []
    names = []
    for i, c2w in enumerate(camera_poses(spec)):
        name = f"images/frame_{i:03d}.png"
        image = (render_view(c2w, spec).numpy() * 255).round().astype(np.uint8)
        Image.fromarray(image).save(out_dir / name)
        frames.append({"file_path": name, "transform_matrix": c2w.tolist()})
        names.append(name)
    meta = {
        "camera_model": "OPENCV",
        "fl_x": spec.focal,
        "fl_y": spec.focal,
        "cx": spec.width / 2,
        "cy": spec.height / 2,
        "w": spec.width,
        "h": spec.height,
        "frames": frames,
        "train_filenames": [names[i] for i in spec.train_ids],
        "val_filenames": [names[i] for i in spec.test_ids],
        "test_filenames": [names[i] for i in spec.test_ids],
    }
    (out_dir / "transforms.json").write_text(json.dumps(meta, indent=2))
    return out_dir


def blender_camera_poses(count: int, radius: float, seed: int) -> List[Tensor]:
    """Cameras all around the object on a hemisphere, as in the NeRF-synthetic scenes: random azimuth,
    elevation 15-65 degrees, looking at the scene's centre."""
    gen = torch.Generator().manual_seed(seed)
    azimuths = torch.rand(count, generator=gen) * 2 * math.pi
    elevations = torch.deg2rad(15.0 + 50.0 * torch.rand(count, generator=gen))
    eyes = radius * torch.stack(
        [elevations.cos() * azimuths.cos(), elevations.cos() * azimuths.sin(), elevations.sin()], dim=-1
    )
    return [look_at(eye, torch.tensor([0.0, 0.0, 0.25])) for eye in eyes]


def write_blender_scene(
    out_dir: Path, spec: SceneSpec = SceneSpec(width=64, height=64, focal=70.0), counts: Tuple[int, int, int] = (12, 2, 8)
) -> Path:
    """The procedural scene in the NeRF-synthetic (Blender) layout: transforms_{train,val,test}.json
    (camera_angle_x; file_path without suffix; transform_matrix camera-to-world, OpenGL axes) and RGBA
    frames r_<i>.png in train/, val/ and test/, ``counts`` frames each, cameras all around the object."""
    out_dir = Path(out_dir)
    for seed, (split, count) in enumerate(zip(("train", "val", "test"), counts)):
        (out_dir / split).mkdir(parents=True, exist_ok=True)
        frames: List[Dict] = []
        for i, c2w in enumerate(blender_camera_poses(count, spec.radius, seed)):
            image = (render_view(c2w, spec, alpha=True).numpy() * 255).round().astype(np.uint8)
            Image.fromarray(image, mode="RGBA").save(out_dir / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "rotation": 0.0, "transform_matrix": c2w.tolist()})
        meta = {"camera_angle_x": 2.0 * math.atan(spec.width / (2.0 * spec.focal)), "frames": frames}
        (out_dir / f"transforms_{split}.json").write_text(json.dumps(meta, indent=2))
    return out_dir


def constant_color_psnr(scene_dir: Path, spec: SceneSpec = SceneSpec()) -> float:
    """PSNR on the test views of predicting the mean training colour everywhere (the baseline to beat)."""
    load = lambda i: np.asarray(Image.open(scene_dir / f"images/frame_{i:03d}.png"), dtype=np.float64) / 255.0  # noqa: E731
    mean = np.mean([load(i).reshape(-1, 3).mean(0) for i in spec.train_ids], axis=0)
    mse = np.mean([np.mean((load(i) - mean) ** 2) for i in spec.test_ids])
    return float(-10.0 * math.log10(mse))


def main(argv: Sequence[str] | None = None) -> None:
    import argparse

    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("out_dir", type=Path)
    args = parser.parse_args(argv)
    print(write_procedural_scene(args.out_dir))


if __name__ == "__main__":
    main()
