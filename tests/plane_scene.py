"""A textured tilted plane seen by cameras looking at the origin, ray-cast exactly: the scene of the sparse-point and
plane-sweep tests."""

import numpy as np
import torch

from frugalnerf_ns.data.procedural_scene import look_at

WIDTH, HEIGHT, FOCAL = 320, 240, 300.0


def camera(eye, target=(0.0, 0.0, 0.0)):
    return look_at(torch.tensor(eye, dtype=torch.float64), torch.tensor(target, dtype=torch.float64),
                   torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64))[:3].double()


def intrinsics(n):
    return torch.tensor([[FOCAL, FOCAL, WIDTH / 2, HEIGHT / 2]], dtype=torch.float64).expand(n, 4)


PLANE_Z = -1.0  # the textured plane z = PLANE_Z - 0.2 x (tilted), textured over x, y in [-2, 2]


def render_plane(c2w, tex):
    """Ray-cast the tilted textured plane into a uint8 image; returns the image."""
    v, u = torch.meshgrid(torch.arange(HEIGHT, dtype=torch.float64) + 0.5, torch.arange(WIDTH, dtype=torch.float64) + 0.5, indexing="ij")
    local = torch.stack([(u - WIDTH / 2) / FOCAL, -(v - HEIGHT / 2) / FOCAL, -torch.ones_like(u)], -1)
    dirs = local @ c2w[:3, :3].T
    origin = c2w[:3, 3]
    # plane: z + 0.2 x = PLANE_Z  ->  t = (PLANE_Z - o_z - 0.2 o_x) / (d_z + 0.2 d_x)
    t = (PLANE_Z - origin[2] - 0.2 * origin[0]) / (dirs[..., 2] + 0.2 * dirs[..., 0])
    hit = origin + dirs * t[..., None]
    size = tex.shape[0]
    tx = ((hit[..., 0] + 2) / 4 * (size - 1)).clamp(0, size - 1).round().long()
    ty = ((hit[..., 1] + 2) / 4 * (size - 1)).clamp(0, size - 1).round().long()
    return (tex[ty.numpy(), tx.numpy()] * 255).astype(np.uint8)
