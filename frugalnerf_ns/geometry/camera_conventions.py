"""Camera conventions of the supported layouts, converted to nerfstudio's (OpenGL: x right, y up, looking
down -z; camera-to-world 3x4). Pure numpy/torch, tested without nerfstudio."""

from __future__ import annotations

from typing import Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor


def llff_to_opengl(poses: np.ndarray) -> np.ndarray:
    """LLFF's camera axes are (down, right, backwards); nerfstudio's are (right, up, backwards)."""
    out = poses.copy()
    out[:, :, 0] = poses[:, :, 1]
    out[:, :, 1] = -poses[:, :, 0]
    return out


def opencv_to_opengl(c2w: np.ndarray) -> np.ndarray:
    """OpenCV cameras look down +z with y down: flip the y and z axes."""
    out = c2w.copy()
    out[..., :3, 1:3] *= -1.0
    return out


def look_at_poses(
    positions: Float[Tensor, "n 3"], target: Float[Tensor, "3"], up: Float[Tensor, "3"]
) -> Float[Tensor, "n 3 4"]:
    """Camera-to-worlds (OpenGL axes) at ``positions`` looking at ``target`` with no roll against ``up``: the one
    look-at frame of the novel-view spiral, the video paths and the procedural scene's cameras."""
    back = torch.nn.functional.normalize(positions - target, dim=-1)
    right = torch.nn.functional.normalize(torch.linalg.cross(up.expand_as(back), back, dim=-1), dim=-1)
    camera_up = torch.linalg.cross(back, right, dim=-1)
    return torch.stack([right, camera_up, back, positions], dim=-1)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def average_pose(poses: np.ndarray) -> np.ndarray:
    """LLFF's mean camera (3x4): mean centre, mean viewing axis, mean up."""
    center = poses[:, :3, 3].mean(axis=0)
    back = _normalize(poses[:, :3, 2].sum(axis=0))
    up = poses[:, :3, 1].sum(axis=0)
    right = _normalize(np.cross(up, back))
    up = np.cross(back, right)
    return np.stack([right, up, back, center], axis=1)


def recenter(poses: np.ndarray, frame: Optional[np.ndarray] = None) -> np.ndarray:
    """Express the poses in the frame of the average camera of ``frame`` (default: the poses themselves), so
    NDC's -z is that mean viewing direction."""
    avg = np.eye(4)
    avg[:3] = average_pose(poses if frame is None else frame)
    homogeneous = np.concatenate([poses[:, :3, :4], np.tile([[[0, 0, 0, 1.0]]], (poses.shape[0], 1, 1))], axis=1)
    return (np.linalg.inv(avg) @ homogeneous)[:, :3]


def decompose_projection(projection: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Split a 3x4 projection P = K [R | t] into K (3x3, K[2,2] = 1) and the OpenCV camera-to-world (3x4)."""
    import cv2

    out = cv2.decomposeProjectionMatrix(projection.astype(np.float64))
    K, R, center = out[0], out[1], out[2]
    K = K / K[2, 2]
    c2w = np.concatenate([R.T, (center[:3] / center[3])], axis=1)
    return K, c2w


def align_cameras(estimate: np.ndarray, reference: np.ndarray) -> Tuple[np.ndarray, float, np.ndarray]:
    """The similarity (R, s, t) with x_ref = s R x_est + t that best puts the ``estimate`` cameras (n x 3 x 4,
    n >= 2) on the ``reference`` ones: R from their orientations (the rotation nearest the mean of
    R_ref_i R_est_i^T, so two cameras suffice, unlike a fit of centres alone), s from the spread of the
    centres about their mean, t from the means."""
    mean = sum(ref[:3, :3] @ est[:3, :3].T for est, ref in zip(estimate, reference))
    u, _, vt = np.linalg.svd(mean)
    rotation = u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt
    est_centres, ref_centres = estimate[:, :3, 3], reference[:, :3, 3]
    est_offsets = est_centres - est_centres.mean(0)
    ref_offsets = ref_centres - ref_centres.mean(0)
    scale = float(np.sqrt((ref_offsets**2).sum() / max((est_offsets**2).sum(), 1e-300)))
    translation = ref_centres.mean(0) - scale * rotation @ est_centres.mean(0)
    return rotation, scale, translation


def apply_similarity(c2w: np.ndarray, rotation: np.ndarray, scale: float, translation: np.ndarray) -> np.ndarray:
    """Camera-to-worlds (n x 3 x 4) moved by x -> s R x + t (orientations turned, centres moved)."""
    out = c2w.copy()
    out[:, :3, :3] = rotation @ c2w[:, :3, :3]
    out[:, :3, 3] = scale * c2w[:, :3, 3] @ rotation.T + translation
    return out
