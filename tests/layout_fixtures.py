"""Tiny synthetic scenes in each supported layout, with a known 3D point and where each camera sees it.

Cameras are built in OpenCV convention (x right, y down, looking down +z), K in pixels of the written
images. Each writer returns the expected pixel (u, v) of POINT in every frame, in filename order.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import List, Tuple

import numpy as np
from PIL import Image

POINT = np.array([0.3, -0.2, 0.25])
WIDTH, HEIGHT = 40, 30


def opencv_cameras(count: int, forward_facing: bool) -> List[Tuple[np.ndarray, np.ndarray]]:
    """(K, world-to-camera 4x4) per frame; forward-facing rigs translate sideways, others circle the point."""
    K = np.array([[36.0, 0.0, 19.0], [0.0, 35.0, 16.0], [0.0, 0.0, 1.0]])
    out = []
    for i in range(count):
        a = (i - (count - 1) / 2) / count
        if forward_facing:
            center = np.array([a * 0.8, 0.1 * np.sin(3 * a), -4.0])
            target = np.array([a * 0.2, 0.0, 5.0])
        else:
            center = 4.0 * np.array([np.sin(a * 1.5), -0.4, -np.cos(a * 1.5)])
            target = np.zeros(3)
        z = target - center
        z /= np.linalg.norm(z)
        x = np.cross(np.array([0.0, -1.0, 0.0]), z)  # y points down in OpenCV
        x /= np.linalg.norm(x)
        y = np.cross(z, x)
        w2c = np.eye(4)
        w2c[:3, :3] = np.stack([x, y, z])
        w2c[:3, 3] = -w2c[:3, :3] @ center
        out.append((K.copy(), w2c))
    return out


def project(K: np.ndarray, w2c: np.ndarray, point: np.ndarray = POINT) -> Tuple[float, float]:
    p = K @ (w2c[:3, :3] @ point + w2c[:3, 3])
    return float(p[0] / p[2]), float(p[1] / p[2])


def write_images(folder: Path, names: List[str], size=(WIDTH, HEIGHT)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i, name in enumerate(names):
        Image.fromarray(np.full((size[1], size[0], 3), 10 * i, dtype=np.uint8)).save(folder / name)


def opengl_c2w(w2c: np.ndarray) -> np.ndarray:
    c2w = np.linalg.inv(w2c)
    c2w[:3, 1:3] *= -1
    return c2w


def write_llff(root: Path, count: int = 10, factor: int = 2, forward_facing: bool = True,
               principal_point: Tuple[float, float] | None = None) -> List[Tuple[float, float]]:
    """poses_bounds.npy at full resolution (factor x the images in images_<factor>/); ``forward_facing`` False:
    the cameras circle the point (an arc of ~80 degrees); ``principal_point`` (full-size pixels; LLFF's rows cannot
    hold it): where the photos' principal point is instead of the centre."""
    cx, cy = (WIDTH / 2, HEIGHT / 2) if principal_point is None else (principal_point[0] / factor, principal_point[1] / factor)
    rows, pixels = [], []
    for K, w2c in opencv_cameras(count, forward_facing=forward_facing):
        c2w = opengl_c2w(w2c)  # columns: right, up, back
        llff = np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3]], axis=1)  # down, right, back
        hwf = np.array([HEIGHT * factor, WIDTH * factor, K[0, 0] * factor])
        rows.append(np.concatenate([np.concatenate([llff, hwf[:, None]], axis=1).ravel(), [1.0, 12.0]]))
        # LLFF has one focal and the principal point at the centre (unless the photos have it elsewhere).
        K_centre = np.array([[K[0, 0], 0, cx], [0, K[0, 0], cy], [0, 0, 1]])
        pixels.append(project(K_centre, w2c))
    root.mkdir(parents=True, exist_ok=True)
    np.save(root / "poses_bounds.npy", np.array(rows))
    write_images(root / f"images_{factor}", [f"image{i:03d}.png" for i in range(count)])
    return pixels


def write_llff_photos(root: Path, count: int = 10, factor: int = 32) -> List[Tuple[float, float]]:
    """An LLFF capture as a phone gives it: poses_bounds.npy and full-size photos in images/ only (here
    factor x 40x30 = 1280x960, which the parser's default brings to 640x480). Pixels in 640x480 units."""
    pixels = write_llff(root, count, factor)
    shutil.rmtree(root / f"images_{factor}")
    write_images(root / "images", [f"image{i:03d}.png" for i in range(count)], size=(WIDTH * factor, HEIGHT * factor))
    to_default = factor / math.ceil(WIDTH * factor / 640)  # the default downscale: long side <= 640 px
    return [(u * to_default, v * to_default) for u, v in pixels]


def write_dtu(root: Path, count: int = 10, factor: int = 4) -> List[Tuple[float, float]]:
    """cameras_sphere.npz whose intrinsics refer to factor x the image size, with a scale matrix."""
    cams, pixels = {}, []
    scale_mat = np.diag([2.0, 2.0, 2.0, 1.0])
    scale_mat[:3, 3] = [0.5, -0.3, 0.2]
    for i, (K, w2c) in enumerate(opencv_cameras(count, forward_facing=False)):
        full = K.copy()
        full[:2] *= factor
        world = np.eye(4)
        world[:3, :4] = full @ w2c[:3]
        # world_mat projects WORLD points; our fixture cameras live in the sphere frame: compose.
        cams[f"world_mat_{i}"] = world @ np.linalg.inv(scale_mat)
        cams[f"scale_mat_{i}"] = scale_mat
        pixels.append(project(K, w2c))
    root.mkdir(parents=True, exist_ok=True)
    np.savez(root / "cameras_sphere.npz", **cams)
    write_images(root / "image", [f"{i:06d}.png" for i in range(count)])
    masks = root / "mask"
    masks.mkdir()
    for i in range(count):
        mask = np.zeros((HEIGHT, WIDTH, 3), dtype=np.uint8)
        mask[5:20, 10:30] = 255
        Image.fromarray(mask).save(masks / f"{i:03d}.png")
    return pixels


def write_realestate(root: Path, count: int = 40) -> List[Tuple[float, float]]:
    intr, extr, pixels = [], [], []
    for K, w2c in opencv_cameras(count, forward_facing=True):
        intr.append(K.ravel())
        extr.append(w2c.ravel())
        pixels.append(project(K, w2c))
    root.mkdir(parents=True, exist_ok=True)
    np.savetxt(root / "CameraIntrinsics.csv", np.array(intr), delimiter=",")
    np.savetxt(root / "CameraExtrinsics.csv", np.array(extr), delimiter=",")
    write_images(root / "rgb", [f"{i:04d}.png" for i in range(count)])
    return pixels


def write_nerfstudio(root: Path, count: int = 10) -> List[Tuple[float, float]]:
    frames, pixels = [], []
    for i, (K, w2c) in enumerate(opencv_cameras(count, forward_facing=False)):
        frames.append({
            "file_path": f"images/frame_{i:05d}.png", "transform_matrix": opengl_c2w(w2c).tolist(),
            "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": WIDTH, "h": HEIGHT,
        })
        pixels.append(project(K, w2c))
    root.mkdir(parents=True, exist_ok=True)
    (root / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}))
    write_images(root / "images", [f"frame_{i:05d}.png" for i in range(count)])
    return pixels


def pixel_rays(cameras, pixels: List[Tuple[float, float]]):
    """World rays (nerfstudio's OpenGL cameras) through continuous pixel positions, one per camera."""
    import torch

    c2w = cameras.camera_to_worlds.double()
    u = torch.tensor([p[0] for p in pixels], dtype=torch.float64)
    v = torch.tensor([p[1] for p in pixels], dtype=torch.float64)
    fx, fy = cameras.fx[:, 0].double(), cameras.fy[:, 0].double()
    cx, cy = cameras.cx[:, 0].double(), cameras.cy[:, 0].double()
    local = torch.stack([(u - cx) / fx, -(v - cy) / fy, -torch.ones_like(u)], dim=-1)
    dirs = torch.einsum("nij,nj->ni", c2w[:, :3, :3], local)
    return c2w[:, :3, 3], torch.nn.functional.normalize(dirs, dim=-1)


def closest_points(o1, d1, o2, d2):
    """Closest points of two rays, and their distances along the rays."""

    w = o1 - o2
    a, b, c = (d1 * d1).sum(), (d1 * d2).sum(), (d2 * d2).sum()
    d, e = (d1 * w).sum(), (d2 * w).sum()
    denom = a * c - b * b
    s = (b * e - c * d) / denom
    t = (a * e - b * d) / denom
    return o1 + s * d1, o2 + t * d2, s, t


def write_colmap(root: Path, count: int = 10, scale: int = 1) -> List[Tuple[float, float]]:
    """COLMAP binary model in sparse/0 (PINHOLE cameras, one 3D point) next to images/ (``scale`` x 40x30
    images and intrinsics: a capture at full size)."""
    from nerfstudio.data.utils import colmap_parsing_utils as cpu

    cameras, images, pixels = {}, {}, []
    for i, (K, w2c) in enumerate(opencv_cameras(count, forward_facing=False)):
        K[:2] *= scale
        cameras[i + 1] = cpu.Camera(id=i + 1, model="PINHOLE", width=WIDTH * scale, height=HEIGHT * scale,
                                    params=np.array([K[0, 0], K[1, 1], K[0, 2], K[1, 2]]))
        images[i + 1] = cpu.Image(id=i + 1, qvec=cpu.rotmat2qvec(w2c[:3, :3]), tvec=w2c[:3, 3], camera_id=i + 1,
                                  name=f"img_{i:03d}.png", xys=np.zeros((0, 2)), point3D_ids=np.zeros(0, dtype=int))
        pixels.append(project(K, w2c))
    points = {1: cpu.Point3D(id=1, xyz=POINT, rgb=np.array([255, 0, 0]), error=0.1,
                             image_ids=np.array([1, 2]), point2D_idxs=np.array([0, 0]))}
    sparse = root / "sparse" / "0"
    sparse.mkdir(parents=True)
    cpu.write_cameras_binary(cameras, sparse / "cameras.bin")
    cpu.write_images_binary(images, sparse / "images.bin")
    cpu.write_points3D_binary(points, sparse / "points3D.bin")
    write_images(root / "images", [f"img_{i:03d}.png" for i in range(count)], size=(WIDTH * scale, HEIGHT * scale))
    return pixels


def write_colmap_photos(root: Path, count: int = 10, scale: int = 32) -> List[Tuple[float, float]]:
    """``write_colmap`` at full size (1280x960): pixels in the units of the parser's default copies (640x480)."""
    pixels = write_colmap(root, count, scale)
    factor = math.ceil(WIDTH * scale / 640)
    return [(u / factor, v / factor) for u, v in pixels]


def write_instant_ngp(root: Path, count: int = 10, k1: float = -0.05) -> List[Tuple[float, float]]:
    """A real capture as instant-ngp's colmap2nerf.py writes it: ``transforms_train.json`` and
    ``transforms_test.json`` (each listing every frame) with one camera (fl_x, fl_y, an off-centre cx, cy, w, h and
    OpenCV distortion), RGB frames with their suffix in ``file_path``. The pixels are the pinhole projections: where
    the point lies in the undistorted frames."""
    frames, pixels = [], []
    K = None
    for i, (K, w2c) in enumerate(opencv_cameras(count, forward_facing=False)):
        frames.append({"file_path": f"./images/frame_{i:05d}.png", "sharpness": 50.0,
                       "transform_matrix": opengl_c2w(w2c).tolist()})
        pixels.append(project(K, w2c))
    meta = {"camera_angle_x": 2 * math.atan(WIDTH / (2 * K[0, 0])), "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2],
            "cy": K[1, 2], "w": WIDTH, "h": HEIGHT, "k1": k1, "k2": 0.0, "p1": 0.0, "p2": 0.0, "aabb_scale": 16,
            "frames": frames}
    root.mkdir(parents=True, exist_ok=True)
    for split in ("train", "test"):
        (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    write_images(root / "images", [f"frame_{i:05d}.png" for i in range(count)])
    return pixels


def llff_capture_as_instant_ngp(scene: Path, root: Path, train: List[int], test: List[int]) -> Path:
    """An LLFF capture with full-size ``images/`` (the shared bird) written as instant-ngp writes a COLMAP capture:
    OpenGL camera-to-worlds in a world turned so the cameras' mean up is +z, moved so the point they look at is the
    origin and scaled so they stand 4 units from it on average; the file's focal length and principal point; the
    JPEG frames (no alpha) copied. ``transforms_train.json`` lists the ``train`` frames, ``transforms_test.json``
    the ``test`` ones."""
    import torch

    from frugalnerf_ns.data.dataparsers.llff import load_poses_bounds
    from frugalnerf_ns.geometry.camera_conventions import llff_to_opengl
    from frugalnerf_ns.geometry.scene_analysis import focus_point

    poses, _ = load_poses_bounds(scene / "poses_bounds.npy")
    c2w = llff_to_opengl(poses[:, :, :4])
    height, width, focal = poses[0, :, 4]
    up = c2w[:, :3, 1].mean(0)
    up /= np.linalg.norm(up)
    axis, angle = np.cross(up, [0.0, 0.0, 1.0]), math.acos(float(np.clip(up[2], -1.0, 1.0)))
    axis = axis / (np.linalg.norm(axis) or 1.0)
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    turn = np.eye(3) + math.sin(angle) * cross + (1 - math.cos(angle)) * cross @ cross  # Rodrigues: up -> +z
    focus = focus_point(torch.from_numpy(c2w)).numpy()
    centres = (c2w[:, :3, 3] - focus) @ turn.T
    scale = 4.0 / np.linalg.norm(centres, axis=-1).mean()
    images = sorted((scene / "images").iterdir())
    root.mkdir(parents=True, exist_ok=True)
    (root / "images").mkdir(exist_ok=True)
    for split, views in (("train", train), ("test", test)):
        frames = []
        for i in views:
            pose = np.eye(4)
            pose[:3, :3] = turn @ c2w[i, :3, :3]
            pose[:3, 3] = centres[i] * scale
            shutil.copy(images[i], root / "images" / images[i].name)
            frames.append({"file_path": f"./images/{images[i].name}", "sharpness": 100.0, "transform_matrix": pose.tolist()})
        meta = {"camera_angle_x": 2 * math.atan(width / (2 * focal)), "camera_angle_y": 2 * math.atan(height / (2 * focal)),
                "fl_x": focal, "fl_y": focal, "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "cx": width / 2, "cy": height / 2,
                "w": width, "h": height, "aabb_scale": 16, "frames": frames}
        (root / f"transforms_{split}.json").write_text(json.dumps(meta, indent=1))
    return root
