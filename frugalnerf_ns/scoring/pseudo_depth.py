"""How right the pseudo depths of cross-scale geometric adaptation are: each scale's rendered depth and the
scale the adaptation picks per ray, scored against a true depth per ray (COLMAP's points in
``scripts/diagnostics/check_pseudo_depth.py``). Pure torch; the picks come from
``model.geometric_adaptation.pseudo_ground_truth_scale``, computed by the caller.
"""

from __future__ import annotations

from typing import Dict

import torch


def summarise(depths: torch.Tensor, truth: torch.Tensor, chosen: torch.Tensor) -> Dict[str, object]:
    """``depths`` (scales, rays), ``truth`` (rays), ``chosen`` (rays; -1 left out)."""
    relative = ((depths - truth[None]).abs() / truth[None])  # scales rays
    closest = relative.argmin(dim=0)
    picked = chosen >= 0
    num_scales = depths.shape[0]
    pseudo = relative.gather(0, chosen.clamp_min(0)[None])[0]
    return {
        "rays": int(truth.numel()),
        "median_relative_error_per_scale": [float(relative[s].median()) for s in range(num_scales)],
        "closest_fraction_per_scale": [float((closest == s).float().mean()) for s in range(num_scales)],
        "picked_fraction_per_scale": [float((chosen == s).float().mean()) for s in range(num_scales)],
        "left_out_fraction": float((~picked).float().mean()),
        "pick_is_closest": float((chosen[picked] == closest[picked]).float().mean()) if picked.any() else float("nan"),
        "pick_is_closest_by_chance": float(sum(
            (closest[picked] == s).float().mean() * (chosen[picked] == s).float().mean() for s in range(num_scales)
        )) if picked.any() else float("nan"),
        "median_relative_error_pseudo": float(pseudo[picked].median()) if picked.any() else float("nan"),
        "median_relative_error_full_same_rays": float(relative[0][picked].median()) if picked.any() else float("nan"),
        "pseudo_closer_than_full": float((pseudo[picked] < relative[0][picked]).float().mean()) if picked.any() else float("nan"),
    }
