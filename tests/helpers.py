"""Builders shared by the tests (small datamanagers and models, the textured-plane scene, development
scripts as modules). Tests import these from here, never from one another."""

from __future__ import annotations

import importlib.util
import math
from pathlib import Path

import torch
from nerfstudio.data.scene_box import SceneBox

from frugalnerf_ns.data.datamanager import FrugalDataManagerConfig
from frugalnerf_ns.data.dataparsers.nerfstudio_format import FewShotNerfstudioDataParserConfig
from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
from frugalnerf_ns.geometry.reprojection import unproject_along_rays

ROOT = Path(__file__).resolve().parents[1]


def load_script(name):
    """A development script of ``scripts/`` as a module (they are not a package)."""
    spec = importlib.util.spec_from_file_location(name, ROOT / "scripts" / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def manager_for(scene, **overrides):
    """A small FrugalNeRF datamanager on ``scene`` (100 training rays in 3x3 patches, 40 novel rays)."""
    fields = dict(train_num_rays_per_batch=100, num_novel_rays_per_batch=40, patch_size=3)
    fields.update(overrides)
    config = FrugalDataManagerConfig(dataparser=FewShotNerfstudioDataParserConfig(data=scene), **fields)
    return config.setup(device="cpu", test_mode="val")


def tiny_model(metadata=None, aabb=((-1.0, -1.0, -1.0), (1.0, 1.0, 1.0)), **overrides):
    """A seeded FrugalNeRF model on a 16^3 -> 24^3 grid (upsampled at steps 2 and 4 of a 10-step schedule)."""
    fields = dict(
        initial_voxels=16**3,
        final_voxels=24**3,
        upsample_at=(0.2, 0.4),  # steps 2 and 4 of a 10-step schedule
        alpha_mask_at=(0.3,),  # step 3
        density_components=(4, 2, 2),
        appearance_components=(8, 2, 2),
        mlp_hidden_dim=16,
        background="white",
        distortion_weight=1e-3,
        density_l1_weight=1e-4,
    )
    fields.update(overrides)
    config = FrugalNeRFModelConfig(**fields)
    box = SceneBox(aabb=torch.tensor(aabb))
    torch.manual_seed(0)
    return config.setup(scene_box=box, num_train_data=3, metadata=metadata or {})


TINY_MODEL = dict(
    initial_voxels=16**3, final_voxels=24**3, upsample_at=(0.5,), alpha_mask_at=(), density_components=(4, 2, 2),
    appearance_components=(8, 2, 2), mlp_hidden_dim=16,
)


def model_for(manager, **overrides):
    """A small model set up from ``manager``'s scene (box, views, the scene analysis' metadata)."""
    config = FrugalNeRFModelConfig(**{**TINY_MODEL, **overrides})
    dataset = manager.train_dataset
    return config.setup(scene_box=dataset.scene_box, num_train_data=len(dataset), metadata=dataset.metadata)


# ---- a textured plane seen by pinhole cameras (geometry tests, pure torch) ---------------------------------
WIDTH, HEIGHT, FOCAL = 64, 48, 50.0
INTRINSICS = torch.tensor([FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2])
PLANE_Z = -3.0


def camera(x=0.0, y=0.0, z=0.0, yaw=0.0):
    """OpenGL camera at (x, y, z) looking down -z, turned by ``yaw`` radians about the y axis."""
    c, s = math.cos(yaw), math.sin(yaw)
    rotation = torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
    return torch.cat([rotation, torch.tensor([[x], [y], [z]])], dim=1)


def pixel_rays(c2w, pixels):
    """Unit world rays through continuous pixel coordinates (the inverse of project_to_camera)."""
    fx, fy, cx, cy = INTRINSICS
    local = torch.stack([(pixels[:, 0] - cx) / fx, -(pixels[:, 1] - cy) / fy, -torch.ones(len(pixels))], dim=-1)
    directions = torch.nn.functional.normalize(local @ c2w[:, :3].T, dim=-1)
    return c2w[:, 3].expand_as(directions), directions


def texture(points):
    """Smooth colour pattern on the plane (varies over a few pixels, so warps are easy to tell apart)."""
    x, y = points[:, 0], points[:, 1]
    return torch.stack([0.5 + 0.4 * torch.sin(9 * x), 0.5 + 0.4 * torch.cos(7 * y), 0.5 + 0.4 * torch.sin(5 * (x + y))], -1)


def plane_depth(origins, directions):
    return (PLANE_Z - origins[:, 2]) / directions[:, 2]


def render_plane(c2w):
    rows, cols = torch.meshgrid(torch.arange(HEIGHT) + 0.5, torch.arange(WIDTH) + 0.5, indexing="ij")
    pixels = torch.stack([cols.flatten(), rows.flatten()], dim=-1)
    origins, directions = pixel_rays(c2w, pixels)
    points = unproject_along_rays(origins, directions, plane_depth(origins, directions))
    return texture(points).reshape(HEIGHT, WIDTH, 3)


def patch_pixels(top=20, left=26, k=5):
    rows, cols = torch.meshgrid(torch.arange(top, top + k) + 0.5, torch.arange(left, left + k) + 0.5, indexing="ij")
    return torch.stack([cols.flatten(), rows.flatten()], dim=-1)
