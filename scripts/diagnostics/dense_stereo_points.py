"""Plane-sweep stereo points (``--pipeline.datamanager.triangulation.dense-stereo``) beside SIFT's triangulated
points on the gate's 2-view splits: count, seconds and, for fern and flower (whose folders hold COLMAP's points
from all their photos), the depth agreement with the full capture (``triangulate_scenes.depth_agreement``).

  python scripts/diagnostics/dense_stereo_points.py [--scenes fern flower horns] [--stereo min_ncc=0.95 ...] [--out outputs/dense_stereo.json]

SIFT runs as the CPU presets run it (2x images); the stereo points are ``sparse_points.stereo_points`` with the
default ``StereoOptions`` but what ``--stereo`` changes (the LLFF near/far bounds as the depth range, as in training).
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.util
import json
import time
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from frugalnerf_ns.data.sparse_points import TriangulationOptions, stereo_points, triangulate_training_views, z_depth_range
from frugalnerf_ns.geometry.plane_sweep import StereoOptions

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("triangulate_scenes", HERE / "triangulate_scenes.py")
triangulate_scenes = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(triangulate_scenes)


def draw(image: np.ndarray, found: dict, path: Path) -> None:
    """The image, then per source the image darkened with its view-0 observations as dots coloured by inverse depth."""
    panels = [image]
    for points in found.values():
        mine = points.view == 0
        uv = points.pixels[mine].round().long()
        inverse = 1.0 / points.depth[mine]
        t = ((inverse - inverse.min()) / (inverse.max() - inverse.min()).clamp_min(1e-9)).numpy()
        colours = np.stack([255 * np.ones_like(t), 255 * t, 255 * (1 - t) * 0.3], -1).astype(np.uint8)  # red far, yellow near
        canvas = (image * 0.35).astype(np.uint8)
        height, width = image.shape[:2]
        for dv in (0, 1):  # 2x2 dots: visible at the image's own size
            for du in (0, 1):
                u = (uv[:, 0] - du).clamp(0, width - 1).numpy()
                v = (uv[:, 1] - dv).clamp(0, height - 1).numpy()
                canvas[v, u] = colours
        panels.append(canvas)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(panels, axis=1)).save(path, quality=90)
    print(f"drew {path}")


def object_masks(config, outputs):
    """The training views' object masks (DTU's ``mask/`` folder, in the order of ``image/``), else None."""
    folder = Path(config.data) / "mask"
    if not folder.is_dir():
        return None
    masks = sorted(folder.glob("*.png"))
    names = sorted(f.name for f in Path(outputs.image_filenames[0]).parent.glob("*.png"))
    return [np.asarray(Image.open(masks[names.index(Path(f).name)]).convert("L")) > 127 for f in outputs.image_filenames]


def fraction_on_object(points, masks) -> float:
    """The share of the observations whose pixel lies on the object (DTU: stereo matches off it are table or backdrop)."""
    uv = points.pixels.round().long()
    hits = [bool(masks[v][min(max(int(y), 0), masks[v].shape[0] - 1), min(max(int(x), 0), masks[v].shape[1] - 1)])
            for v, (x, y) in zip(points.view.tolist(), uv.tolist())]
    return float(np.mean(hits)) if hits else float("nan")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", nargs="+", default=["fern", "flower", "horns"], choices=sorted(triangulate_scenes.SCENES))
    parser.add_argument("--stereo", nargs="*", default=[], metavar="FIELD=VALUE",
                        help="StereoOptions fields to change, e.g. min_ncc=0.95 plane_step_pixels=0.5")
    parser.add_argument("--out", type=Path, default=Path("outputs/dense_stereo.json"))
    parser.add_argument("--draw", type=Path, default=None, help="folder for one picture per scene: the first training "
                        "view, its SIFT observations, its stereo observations coloured by inverse depth (near: yellow)")
    args = parser.parse_args(argv)
    fields = {f.name: f.type for f in dataclasses.fields(StereoOptions)}
    changes = {}
    for item in args.stereo:
        name, _, value = item.partition("=")
        if name not in fields:
            parser.error(f"--stereo {item}: StereoOptions has no field {name!r} (it has {', '.join(fields)})")
        changes[name] = int(value) if fields[name] in (int, "int") else float(value)
    stereo_options = dataclasses.replace(StereoOptions(), **changes)
    rows = []
    for name in args.scenes:
        config = triangulate_scenes.SCENES[name]
        outputs = config.setup().get_dataparser_outputs("train")
        cameras = outputs.cameras
        images = [np.asarray(Image.open(f).convert("RGB")) for f in outputs.image_filenames]
        k = torch.stack([cameras.fx[:, 0], cameras.fy[:, 0], cameras.cx[:, 0], cameras.cy[:, 0]], -1).double()
        c2w = cameras.camera_to_worlds.double()
        near_far = (outputs.metadata or {}).get("near_far")
        options = TriangulationOptions(sift_upsample=2)
        start = time.time()
        sift = triangulate_training_views(images, c2w, k, options, None if near_far is None else tuple(map(float, near_far)), progress=False)
        found = {"SIFT 2x": (sift, time.time() - start)}
        # As training picks it: the scene's near/far, else SIFT's points' z-depths widened (DTU).
        bounds = tuple(map(float, near_far)) if near_far is not None else z_depth_range(sift, c2w, k)
        if bounds is not None:
            start = time.time()
            found["plane-sweep stereo"] = (stereo_points(images, c2w, k, bounds, options, progress=False, stereo=stereo_options),
                                           time.time() - start)
        if args.draw is not None:
            draw(images[0], {source: points for source, (points, _) in found.items()}, args.draw / f"{name}_stereo_points.jpg")
        masks = object_masks(config, outputs)
        for source, (points, seconds) in found.items():
            rows.append({"scene": name, "source": source, "points": points.num_points, "observations": int(points.view.numel()),
                         "seconds": seconds, "depth_range": list(bounds) if bounds is not None else None,
                         **triangulate_scenes.depth_agreement(points, outputs, k, config)})
            if masks is not None:
                rows[-1]["fraction_on_object"] = fraction_on_object(points, masks)
            print(rows[-1], flush=True)
    print("| scene | points from | points | seconds | compared with the full capture | median / p90 relative depth "
          "difference | above 10 % |\n|---|---|---|---|---|---|---|")
    for row in rows:
        agree = (f"{row['median_relative_depth_difference']:.3f} / {row['p90_relative_depth_difference']:.3f} | "
                 f"{row['fraction_above_10_percent']:.3f}") if row.get("compared") else " | "
        if "fraction_on_object" in row:
            agree += f" on the object mask: {row['fraction_on_object']:.2f}"
        print(f"| {row['scene']} | {row['source']} | {row['points']} | {row['seconds']:.1f} | {row.get('compared', '')} | {agree} |")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"stereo": dataclasses.asdict(stereo_options), "rows": rows}, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
