"""``frugalnerf-next-view --load-config <run>/config.yml``: where to take the next photo, from a trained run.

Candidate viewpoints lie on the surface the photos span (``geometry/viewpoints.py``); each is rendered small with
every scale and scored by what a photo from there would teach the model (``scoring/next_view.py``). Written into
the run folder:

- ``next_view.json``: the best ``--count`` candidates, best first: the camera (in the frame the run renders in, and
  in the data's own frame), the score and its signals, a description relative to the photos; and the largest-gap
  viewpoint for comparison;
- ``next_view_camera_path.json``: a nerfstudio camera path through the suggestions (``ns-render camera-path
  --camera-path-filename <it>``; the viewer's render panel lists it when it also sits in ``<data>/camera_paths/``,
  where it is copied unless ``--no-viewer-copy``);
- ``next_view.png``: each suggestion's render beside a map of where the model is unsure there (red: no photo sees
  it; yellow: one photo sees it; blue: light from beyond the modelled box): what the next photo should capture.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
import textwrap
import time
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Dict, Iterator, List, Optional, Sequence, Tuple

import torch

from frugalnerf_ns.errors import UserError

SCORE_SIDE = 64
"""Longest side (pixels) of the candidate renders that are scored: ~2-3k rays each."""
PICTURE_SIDE = 240


@dataclass
class Suggestion:
    camera_to_world: torch.Tensor
    score: float
    signals: Dict[str, float]
    description: str


@contextmanager
def all_scales(model) -> Iterator[None]:
    """Inference renders every scale inside the block (the scales' depth disagreement is a signal)."""
    previous = getattr(model, "num_rendered_scales", None)
    model.num_rendered_scales = model.field.num_scales
    try:
        yield
    finally:
        model.num_rendered_scales = previous


def _render(model, camera, scales: bool) -> Dict[str, torch.Tensor]:
    """Every output of one camera's render: the full scale only, or every scale with ``scales``."""
    bundle = camera.generate_rays(camera_indices=0, keep_shape=True)
    which = all_scales(model) if scales else model.full_scale_only()
    with torch.no_grad(), which:
        outputs = model.get_outputs_for_camera_ray_bundle(bundle.to(model.device))
    return {"origins": bundle.origins.reshape(-1, 3).cpu(), "directions": bundle.directions.reshape(-1, 3).cpu(),
            **{k: v.cpu() for k, v in outputs.items() if isinstance(v, torch.Tensor)}}


def small_cameras(cameras, side: int):
    """A copy of ``cameras`` rescaled so the longest image side is about ``side`` pixels (never enlarged)."""
    copy = cameras[torch.arange(len(cameras))]
    longest = float(max(int(copy.width[0]), int(copy.height[0])))
    copy.rescale_output_resolution(min(1.0, side / longest), scale_rounding_mode="round")
    return copy


class Scorer:
    """Renders candidates of one trained pipeline and turns the renders into signals."""

    def __init__(self, pipeline, side: int = SCORE_SIDE, scales: bool = False) -> None:
        self.model = pipeline.model
        self.datamanager = pipeline.datamanager
        self.side = side
        self.scales = scales  # render the lower scales too (the depth-disagreement signal needs them)
        self.photos = small_cameras(self.datamanager.train_dataset.cameras, side)
        self.has_room = bool(getattr(self.model, "has_room", False))
        self.photo_c2w, self.photo_k, self.photo_depths = [], [], []
        for index in range(len(self.photos)):
            camera = self.photos[index : index + 1]
            out = _render(self.model, camera, scales=False)
            height, width = int(camera.height), int(camera.width)
            self.photo_c2w.append(camera.camera_to_worlds[0].cpu())
            self.photo_k.append(torch.tensor([float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy)]))
            self.photo_depths.append(out["depth"].reshape(height, width))

    def render_signals(self, camera_to_world: torch.Tensor, side: Optional[int] = None, scales: Optional[bool] = None):
        """(per-pixel signals, render) of a viewpoint, with the photos' intrinsics at ``side`` (default: the
        scoring size), every scale rendered with ``scales`` (default: the scorer's choice)."""
        from frugalnerf_ns.data.novel_cameras import cameras_at
        from frugalnerf_ns.model.rendering import scale_suffix
        from frugalnerf_ns.scoring.next_view import pixel_signals

        intrinsics = self.photos if side is None else small_cameras(self.datamanager.train_dataset.cameras, side)
        camera = cameras_at(camera_to_world[None].float(), intrinsics[0:1])
        out = _render(self.model, camera, self.scales if scales is None else scales)
        depths = [out["depth"].reshape(-1)]
        scale = 1
        while f"depth{scale_suffix(scale)}" in out:
            depths.append(out[f"depth{scale_suffix(scale)}"].reshape(-1))
            scale += 1
        signals = pixel_signals(out["origins"], out["directions"], depths, out["accumulation"].reshape(-1),
                                self.photo_c2w, self.photo_k, self.photo_depths, has_room=self.has_room)
        return signals, out["rgb"].reshape(int(camera.height), int(camera.width), 3)


def wants_next_view(pipeline) -> bool:
    """Whether a training ends with a suggestion: photos without cameras, or a capture around a subject whose room is
    modelled beyond the box (what a user holding a phone takes); not the benchmark layouts (LLFF forward-facing
    scenes, DTU, synthetic objects), whose photos are fixed."""
    from frugalnerf_ns.data.dataparsers.auto import AutoDataParserConfig, detect_layout
    from frugalnerf_ns.data.dataparsers.photos import PhotosDataParserConfig

    parser = pipeline.datamanager.config.dataparser
    kind = detect_layout(Path(parser.data))[1] if isinstance(parser, AutoDataParserConfig) else type(parser)
    return issubclass(kind, PhotosDataParserConfig) or bool(getattr(pipeline.model, "has_room", False))


def run_folder(config_path: Path) -> Path:
    return config_path.parent


def load_pipeline(config_path: Path):
    """The trained pipeline of a run, or one line saying why not."""
    if not config_path.is_file():
        raise UserError(f"{config_path} is not a run's config.yml (pass --load-config <run>/config.yml)")
    checkpoints = run_folder(config_path) / "nerfstudio_models"
    if not any(checkpoints.glob("step-*.ckpt")):
        raise UserError(f"{config_path}: the run has no checkpoint in {checkpoints} (train it first, or wait for its "
                        "first save)")
    from nerfstudio.utils.eval_utils import eval_setup

    from frugalnerf_ns.errors import one_line_errors
    from frugalnerf_ns.tools.offline_tools import patch_torchmetrics_lpips

    patch_torchmetrics_lpips()
    try:
        with one_line_errors():
            _, pipeline, _, _ = eval_setup(config_path, test_mode="test")
    except SystemExit:
        raise
    except (FileNotFoundError, OSError, ValueError, KeyError) as err:
        raise UserError(f"{config_path}: the run's scene cannot be read ({type(err).__name__}: {err})") from None
    if not hasattr(pipeline.datamanager, "scene_type"):
        raise UserError(f"{config_path} is not a FrugalNeRF run (frugalnerf-next-view reads FrugalNeRF runs only)")
    pipeline.eval()
    return pipeline


def data_frame_pose(camera_to_world: torch.Tensor, dataparser_outputs) -> List[List[float]]:
    """The camera in the data's own frame: the dataparser's transform and scale undone (nerfstudio's
    ``transform_poses_to_original_space``; the data's world axes, the camera's axes OpenGL's)."""
    pose = camera_to_world.detach().cpu().float()[None]
    return dataparser_outputs.transform_poses_to_original_space(pose, camera_convention="opengl")[0].tolist()


def distinct_best(poses_best_first: Sequence[torch.Tensor], count: int, spacing_factor: float = 1.5) -> List[int]:
    """Indices of up to ``count`` poses, best first, none next to one already taken (closer than ``spacing_factor``
    times the typical distance between neighbouring candidates): three suggestions that differ. Where too few are
    apart, the best of the rest fill up."""
    centres = torch.stack([pose[:3, 3].double() for pose in poses_best_first])
    if len(centres) < 2:
        return list(range(len(centres)))[:count]
    distance = torch.cdist(centres, centres)
    spacing = float(distance.masked_fill(torch.eye(len(centres), dtype=torch.bool), float("inf")).min(dim=1).values.median())
    taken: List[int] = []
    for index in range(len(centres)):
        if len(taken) == count:
            break
        if all(float(distance[index, other]) >= spacing_factor * spacing for other in taken):
            taken.append(index)
    taken += [i for i in range(len(centres)) if i not in taken][: count - len(taken)]
    return taken


def rank_candidates(pipeline, count: int = 3, step_degrees: float = 10.0, score: Optional[str] = None,
                    scorer: Optional[Scorer] = None) -> Tuple[List[Suggestion], Dict[str, object]]:
    """The ``count`` best candidate viewpoints of a trained pipeline, best first, and facts about the ranking."""
    from frugalnerf_ns.geometry.viewpoints import candidate_poses, describe, largest_gap_pose, separations, subject_frame
    from frugalnerf_ns.scoring.next_view import BLOCKED_FRACTION, SCORES, SCORES_NEEDING_SCALES, default_score

    if score is not None and score not in SCORES:
        raise UserError(f"--score must be one of {', '.join(SCORES)} (got {score!r})")
    datamanager = pipeline.datamanager
    photos = datamanager.train_dataset.cameras.camera_to_worlds.cpu()
    names = [Path(f).name for f in datamanager.train_dataparser_outputs.image_filenames]
    forward = datamanager.scene_type == "forward-facing"
    frame = None if forward else subject_frame(photos, datamanager.scene_layout.focus)
    depth = datamanager.spiral_focus_depth() if forward else None
    candidates = candidate_poses(photos, forward, frame, step_degrees, look_at_depth=depth)
    score = score or default_score(candidates.layout)
    scorer = scorer or Scorer(pipeline, scales=score in SCORES_NEEDING_SCALES)
    subject = candidates.subject.double()
    apart = separations(candidates.camera_to_worlds, photos, forward, frame)
    scored, blocked = [], 0
    for pose, separation in zip(candidates.camera_to_worlds, apart.tolist()):
        signals = replace(scorer.render_signals(pose)[0].summary(), separation=separation)
        # A viewpoint inside the subject or behind a wall of the room sees a surface right in front of it: its render
        # says nothing about the scene. The geometric score reads no render: the model's density where no photo
        # looked (the far side of a subject) is a guess, and would hide the very viewpoints that score highest.
        if score != "largest_gap" and signals.median_depth < BLOCKED_FRACTION * float((pose[:3, 3].double() - subject).norm()):
            blocked += 1
            continue
        scored.append((SCORES[score](signals), pose, signals))
    if not scored:
        raise UserError("every candidate viewpoint is blocked by the model's geometry (inside the subject or a wall)")
    scored.sort(key=lambda item: -item[0])
    chosen = distinct_best([pose for _, pose, _ in scored], count)
    suggestions = [Suggestion(pose, value, signals.as_dict(), describe(pose, photos, names, forward, frame))
                   for value, pose, signals in (scored[i] for i in chosen)]
    facts: Dict[str, object] = {"score": score, "candidates": len(scored), "blocked": blocked, "layout": candidates.layout,
                                "scene_type": datamanager.scene_type}
    if not forward:
        gap_pose, gap = largest_gap_pose(photos, frame)
        facts["largest_gap"] = {"degrees": gap, "camera_to_world": gap_pose.tolist(),
                                "description": describe(gap_pose, photos, names, forward, frame)}
    return suggestions, facts


def camera_path(suggestions: Sequence[Suggestion], camera, seconds_each: float = 1.0) -> Dict[str, object]:
    """A nerfstudio camera path through the suggestions: keyframes (the viewer's render panel) and one frame per
    suggestion (``ns-render camera-path``), with the photos' field of view and aspect."""
    width, height = int(camera.width), int(camera.height)
    fov = math.degrees(2.0 * math.atan(height / (2.0 * float(camera.fy))))
    frames = []
    for suggestion in suggestions:
        matrix = torch.eye(4)
        matrix[:3] = suggestion.camera_to_world.float()
        frames.append({"matrix": matrix.flatten().tolist(), "fov": fov, "aspect": width / height})
    return {
        "camera_type": "perspective", "render_height": height, "render_width": width, "fps": 1.0 / seconds_each,
        "seconds": seconds_each * len(frames), "default_fov": fov, "default_transition_sec": seconds_each,
        "is_cycle": False, "smoothness_value": 0.0,
        "keyframes": frames,
        "camera_path": [{"camera_to_world": f["matrix"], "fov": fov, "aspect": f["aspect"]} for f in frames],
    }


UNSURE_COLOURS = {"unseen": (1.0, 0.15, 0.1), "single": (1.0, 0.85, 0.1), "beyond": (0.2, 0.45, 1.0)}


def unsure_map(signals, height: int, width: int) -> torch.Tensor:
    """[H, W, 3] map of where the model is unsure: red where no photo sees the surface, yellow where one photo does,
    blue as much as the light comes from beyond the box, dark grey where two or more photos see it."""
    picture = torch.full((height * width, 3), 0.15)
    single = signals.seen_by == 1
    unseen = signals.seen_by == 0
    picture[single] = torch.tensor(UNSURE_COLOURS["single"])
    picture[unseen] = torch.tensor(UNSURE_COLOURS["unseen"])
    beyond = signals.beyond[:, None].clamp(0, 1)
    picture = picture * (1 - beyond) + beyond * torch.tensor(UNSURE_COLOURS["beyond"])
    return picture.reshape(height, width, 3)


def write_picture(rows: Sequence[Tuple[torch.Tensor, torch.Tensor, str]], path: Path) -> None:
    """One row per suggestion: its render, its unsure map, a caption above."""
    import numpy as np
    from PIL import Image, ImageDraw

    caption_height = 34
    height, width = rows[0][0].shape[:2]
    canvas = Image.new("RGB", (2 * width + 12, len(rows) * (height + caption_height) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    for i, (rgb, unsure, caption) in enumerate(rows):
        top = i * (height + caption_height)
        for column, image in enumerate((rgb, unsure)):
            array = (image.clamp(0, 1).numpy() * 255).astype(np.uint8)
            canvas.paste(Image.fromarray(array), (4 + column * (width + 4), top + caption_height))
        lines = textwrap.wrap(caption, width=max(20, (2 * width) // 6))[:2]
        for j, line in enumerate(lines):
            draw.text((4, top + 2 + 15 * j), line, fill=(0, 0, 0))
    canvas.save(path)


def suggest(config_path: Path, count: int = 3, step_degrees: float = 10.0, score: Optional[str] = None,
            viewer_copy: bool = True, pipeline=None, print_fn=print) -> Dict[str, object]:
    """Ranks and writes ``next_view.json``, the camera path and the picture into the run folder; returns the
    JSON written."""
    from frugalnerf_ns.scoring.next_view import SCORES_NEEDING_SCALES

    started = time.time()
    pipeline = pipeline or load_pipeline(config_path)
    folder = run_folder(config_path)
    scorer = Scorer(pipeline, scales=score in SCORES_NEEDING_SCALES)
    suggestions, facts = rank_candidates(pipeline, count, step_degrees, score, scorer)
    rows = []
    for rank, suggestion in enumerate(suggestions, start=1):
        signals, rgb = scorer.render_signals(suggestion.camera_to_world, PICTURE_SIDE, scales=False)
        rows.append((rgb, unsure_map(signals, *rgb.shape[:2]), f"{rank}. {suggestion.description}"))
    write_picture(rows, folder / "next_view.png")
    path = camera_path(suggestions, pipeline.datamanager.train_dataset.cameras[0:1])
    (folder / "next_view_camera_path.json").write_text(json.dumps(path, indent=1))
    outputs = pipeline.datamanager.train_dataparser_outputs
    record = {
        **facts, "seconds": round(time.time() - started, 1),
        "suggestions": [{"rank": rank, "score": s.score, "signals": s.signals, "description": s.description,
                         "camera_to_world": s.camera_to_world.tolist(),
                         "camera_to_world_data_frame": data_frame_pose(s.camera_to_world, outputs)}
                        for rank, s in enumerate(suggestions, start=1)],
        "camera_convention": "camera-to-world 3x4, OpenGL camera axes (x right, y up, looking down -z); "
                             "camera_to_world: the frame the run renders in (ns-render, the viewer); "
                             "camera_to_world_data_frame: the data's own world frame (its poses file)",
    }
    (folder / "next_view.json").write_text(json.dumps(record, indent=1))
    copied = ""
    if viewer_copy:
        target = Path(pipeline.datamanager.config.dataparser.data) / "camera_paths"
        try:
            target.mkdir(exist_ok=True)
            shutil.copyfile(folder / "next_view_camera_path.json", target / "next_view.json")
            copied = f"; the viewer's render panel lists it as {target / 'next_view.json'}"
        except OSError:
            copied = f"; copy it into {target} for the viewer's render panel"
    if suggestions:
        print_fn(f"frugalnerf: next photo: {suggestions[0].description} (score {suggestions[0].score:.2f}); "
                 f"{len(suggestions)} suggestions in {folder / 'next_view.json'}, pictures in next_view.png, "
                 f"camera path next_view_camera_path.json{copied}")
    return record


def main(argv: Optional[Sequence[str]] = None) -> None:
    parser = argparse.ArgumentParser(prog="frugalnerf-next-view", description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    parser.add_argument("--load-config", type=Path, required=True, help="config.yml of a trained FrugalNeRF run")
    parser.add_argument("--count", type=int, default=3, help="suggestions to write (default 3)")
    parser.add_argument("--step-degrees", type=float, default=10.0, help="azimuth between candidates around a subject")
    parser.add_argument("--score", default=None, help="candidate score (default: largest_gap around a subject, "
                        "unseen_or_single beside forward-facing photos: the measured choice)")
    parser.add_argument("--no-viewer-copy", action="store_true", help="do not copy the camera path into <data>/camera_paths/")
    args = parser.parse_args(argv)
    if args.count < 1:
        sys.exit("frugalnerf: error: --count must be at least 1")
    if not 1.0 <= args.step_degrees <= 90.0:
        sys.exit("frugalnerf: error: --step-degrees must be between 1 and 90")
    try:
        suggest(args.load_config, args.count, args.step_degrees, args.score, not args.no_viewer_copy)
    except UserError as err:
        sys.exit(str(err))


if __name__ == "__main__":
    main()
