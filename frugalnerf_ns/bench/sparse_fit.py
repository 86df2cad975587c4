"""How closely a run's depth meets the sparse points L_sd pulls it to: the summary printed by
``scripts/diagnostics/sparse_depth_fit.py``, with L_sd's own term (``model.losses.inverse_depth_term``). Pure torch."""

from __future__ import annotations

from typing import Dict, List

import torch

from frugalnerf_ns.model.losses import inverse_depth_term


def depth_agreement(rendered: torch.Tensor, target: torch.Tensor) -> Dict[str, float]:
    """Per observation, ``rendered`` (the run's depth on the ray through the point's pixel) against ``target`` (the
    point's depth): the relative difference |rendered - target| / target (median, p90, share above 10 %) and L_sd's
    own term, the mean of (1/rendered - 1/target)^2."""
    if target.numel() == 0:
        return {"observations": 0}
    relative = (rendered - target).abs() / target
    return {"observations": int(target.numel()), "median_relative": float(relative.median()),
            "p90_relative": float(relative.quantile(0.9)), "above_10_percent": float((relative > 0.1).double().mean()),
            "mean_inverse_depth_term": float(inverse_depth_term(rendered, target).mean())}


def agreement_by_depth(rendered: torch.Tensor, target: torch.Tensor, bins: int = 4) -> List[Dict[str, float]]:
    """``depth_agreement`` per band of the points' depth (``bins`` bands of equal counts, nearest first), each with
    its depth range and its share of the summed L_sd term: in NDC a far point's relative depth is loosely held
    (the space is uniform in inverse depth), while L_sd's term, also in inverse depth, weighs it little."""
    order = torch.argsort(target)
    total = float(inverse_depth_term(rendered, target).sum())
    bands = []
    for chosen in torch.tensor_split(order, bins):
        if chosen.numel() == 0:
            continue
        band = depth_agreement(rendered[chosen], target[chosen])
        band.update(depth_from=float(target[chosen].min()), depth_to=float(target[chosen].max()),
                    share_of_term=band["mean_inverse_depth_term"] * chosen.numel() / total if total > 0 else float("nan"))
        bands.append(band)
    return bands
