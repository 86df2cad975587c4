"""How much a photo from a candidate viewpoint would teach the model: signals from its render there (pure torch).

A candidate is rendered at a small size with every scale; each pixel's surface point (ray origin + depth x unit
direction) is reprojected into every photo, occlusion-tested against the photo's own rendered depth
(``geometry/visibility.py``): hidden only where it lies more than ``tolerance`` of its distance behind the photo's
surface (two renders of an unsure model rarely agree closer). The signals, each a mean over the candidate's pixels in [0, 1]:

- ``unseen``: no photo sees the point: its colour and depth there are guessed;
- ``single``: exactly one photo sees it: colour is known, depth is not (nothing to triangulate or warp against);
- ``disagreement``: the scales' depths disagree (relative spread of the lower scales' depths around the full
  scale's, clipped at 1): what cross-scale geometric adaptation could not settle;
- ``beyond``: the light that comes from beyond the modelled box (1 - the box's accumulation), where only a
  coarse model of the room answers.

``SCORES`` combines them; the one ``frugalnerf-next-view`` ranks by was chosen by measurement
(docs/notes/next-view.md).
"""

from __future__ import annotations

from dataclasses import dataclass, asdict
from typing import Callable, Dict, Sequence

import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.geometry.visibility import training_view_coverage


@dataclass(frozen=True)
class ViewSignals:
    unseen: float
    single: float
    disagreement: float
    beyond: float
    median_depth: float
    """Median distance to the surface the candidate sees (a viewpoint inside the subject sees one right away)."""
    separation: float = 0.0
    """How far the candidate stands from the nearest photo, in [0, 1]: around a subject the azimuth to the nearest
    photo over 180 degrees; beside forward-facing photos the distance over their widest baseline (clipped)."""

    def as_dict(self) -> Dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class PixelSignals:
    """Per pixel of one candidate render: how many photos see its surface point, the scales' depth disagreement,
    the light from beyond the box."""

    seen_by: Tensor
    disagreement: Tensor
    beyond: Tensor
    depth: Tensor

    def summary(self) -> ViewSignals:
        return ViewSignals(
            unseen=float((self.seen_by == 0).float().mean()),
            single=float((self.seen_by == 1).float().mean()),
            disagreement=float(self.disagreement.mean()),
            beyond=float(self.beyond.mean()),
            median_depth=float(self.depth.median()),
        )


def scale_depth_disagreement(depths: Sequence[Float[Tensor, " pixels"]]) -> Float[Tensor, " pixels"]:
    """Largest relative distance of a lower scale's depth from the full scale's (``depths[0]``), clipped to [0, 1];
    zeros with one scale."""
    full = depths[0].clamp(min=1e-6)
    if len(depths) < 2:
        return torch.zeros_like(full)
    spread = torch.stack([(d - depths[0]).abs() for d in depths[1:]]).max(dim=0).values
    return (spread / full).clamp(0.0, 1.0)


def pixel_signals(
    origins: Float[Tensor, "pixels 3"],
    directions: Float[Tensor, "pixels 3"],
    depths: Sequence[Float[Tensor, " pixels"]],
    accumulation: Float[Tensor, " pixels"],
    photo_camera_to_worlds: Sequence[Float[Tensor, "3 4"]],
    photo_intrinsics: Sequence[Float[Tensor, "4"]],
    photo_depths: Sequence[Float[Tensor, "height width"]],
    tolerance: float = 0.1,
    has_room: bool = False,
) -> PixelSignals:
    """The signals of one candidate render (``depths``: one per scale, full scale first, distances along the unit
    ``directions``), against the photos' cameras and their rendered depths (at any one size with matching
    intrinsics). ``has_room``: the scene models space beyond its box, so ``1 - accumulation`` is light from there
    (without a room, it is the background colour and counts as nothing)."""
    points = origins + directions * depths[0][:, None]
    images = [torch.zeros(*d.shape, 3, dtype=points.dtype, device=points.device) for d in photo_depths]
    coverage = training_view_coverage(points, list(photo_camera_to_worlds), list(photo_intrinsics),
                                      list(photo_depths), images, tolerance, occlusion_only=True)
    beyond = (1.0 - accumulation).clamp(0.0, 1.0) if has_room else torch.zeros_like(accumulation)
    return PixelSignals(coverage.seen_by, scale_depth_disagreement(depths), beyond, depths[0])


SCORES: Dict[str, Callable[[ViewSignals], float]] = {
    "unseen": lambda s: s.unseen,
    "unseen_or_single": lambda s: s.unseen + s.single,
    "single": lambda s: s.single,
    "disagreement": lambda s: s.disagreement,
    "beyond": lambda s: s.beyond,
    "coverage_and_disagreement": lambda s: s.unseen + 0.5 * s.single + s.disagreement,
    "largest_gap": lambda s: s.separation,
}
"""Candidate scores (higher: the photo would teach more), compared in docs/notes/next-view.md."""

DEFAULT_SCORE = "unseen_or_single"
DEFAULT_SCORE_BY_LAYOUT = {"ring": "largest_gap", "plane": "unseen_or_single"}
"""The measured choice (docs/notes/next-view.md): around a subject the middle of the largest gap between the photos
trained as well as the render-based score or better (2 captures, one seed each), so it ranks by default there;
beside forward-facing photos (one split measured) the render-based score picked the better frame."""


def default_score(layout: str) -> str:
    """The score candidates of a layout ("ring" or "plane") are ranked by unless one is asked for."""
    return DEFAULT_SCORE_BY_LAYOUT.get(layout, DEFAULT_SCORE)
SCORES_NEEDING_SCALES = {"disagreement", "coverage_and_disagreement"}
"""Scores that read the lower scales' depths (the candidates are then rendered at every scale, ~2x slower)."""
BLOCKED_FRACTION = 0.25
"""A candidate whose median surface distance is under this fraction of its distance to the subject stands inside
the subject or behind a wall of the modelled room: it is not suggested."""
