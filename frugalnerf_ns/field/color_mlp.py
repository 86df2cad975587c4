"""The colour MLP shared by every scale: tinycudann when it can run, an equivalent torch MLP otherwise.

Both implementations sit behind one interface (features, directions) -> rgb in [0, 1], so the field never
asks which one it holds. tinycudann is built from source on GPU machines only; CPU machines use torch.
"""

from __future__ import annotations

import importlib
from typing import Literal, Optional

import torch
from jaxtyping import Float
from torch import Tensor, nn

MLPImplementation = Literal["auto", "tcnn", "torch"]


def positional_encoding(x: Float[Tensor, "n d"], num_frequencies: int) -> Float[Tensor, "n d2"]:
    """TensoRF's encoding of features / directions: sin and cos at frequencies 2^0 .. 2^(F-1) (no identity)."""
    if num_frequencies <= 0:
        return x.new_zeros(x.shape[0], 0)
    freqs = 2.0 ** torch.arange(num_frequencies, device=x.device, dtype=x.dtype)
    scaled = (x[..., None] * freqs).reshape(x.shape[0], -1)
    return torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)


def tcnn_available() -> bool:
    """tinycudann is importable and a CUDA device exists (it has no CPU path)."""
    if not torch.cuda.is_available():
        return False
    try:
        importlib.import_module("tinycudann")
    except (ImportError, OSError):
        return False
    return True


def choose_implementation(requested: MLPImplementation) -> Literal["tcnn", "torch"]:
    """Resolve ``auto``; an explicit ``tcnn`` request fails clearly where tinycudann cannot run."""
    if requested == "torch":
        return "torch"
    available = tcnn_available()
    if requested == "tcnn" and not available:
        raise RuntimeError(
            "color_mlp_implementation='tcnn' was requested but tinycudann is not importable or no CUDA "
            "device is present; use 'auto' or 'torch' (install it with `pip install .[tcnn]` on a GPU machine)"
        )
    return "tcnn" if available else "torch"


_NATIVE_BFLOAT16: dict = {}


def native_bfloat16() -> bool:
    """Whether this CPU multiplies bfloat16 matrices in hardware (AVX512-BF16 or AMX on x86 Linux): there a colour
    MLP's hidden layers ran ~1.9x faster in bfloat16 (``ColorMLP.forward_bfloat16``; AVX512-BF16, 2 cores);
    elsewhere float32 is kept. Read once from /proc/cpuinfo (False where it cannot be read)."""
    if "value" not in _NATIVE_BFLOAT16:
        try:
            with open("/proc/cpuinfo", encoding="ascii", errors="replace") as info:
                flags = next((line.split(":", 1)[1].split() for line in info if line.startswith("flags")), [])
        except OSError:
            flags = []
        _NATIVE_BFLOAT16["value"] = "avx512_bf16" in flags or "amx_bf16" in flags
    return _NATIVE_BFLOAT16["value"]


class ColorMLP(nn.Module):
    """rgb = sigmoid(MLP([features, PE(features), dir, PE(dir)])); which inputs are used is configured.

    Args:
        feature_dim: appearance feature size after the shared basis matrix (27 in the paper).
        hidden_dim: width of the two hidden layers.
        feature_pe: frequencies of the features' positional encoding (0: none).
        use_view_dirs: feed the viewing direction.
        view_pe: frequencies of the direction's positional encoding (0: none).
        implementation: "auto" picks tinycudann when it can run, else torch.
    """

    def __init__(
        self,
        feature_dim: int,
        hidden_dim: int = 128,
        feature_pe: int = 0,
        use_view_dirs: bool = False,
        view_pe: int = 0,
        implementation: MLPImplementation = "auto",
    ) -> None:
        super().__init__()
        self.feature_pe = feature_pe
        self.use_view_dirs = use_view_dirs
        self.view_pe = view_pe if use_view_dirs else 0
        in_dim = feature_dim + 2 * feature_pe * feature_dim
        if use_view_dirs:
            in_dim += 3 + 2 * self.view_pe * 3
        self.in_dim = in_dim
        self.implementation = choose_implementation(implementation)
        if self.implementation == "tcnn":
            tcnn = importlib.import_module("tinycudann")
            self.net: nn.Module = tcnn.Network(
                n_input_dims=in_dim,
                n_output_dims=3,
                network_config={
                    "otype": "FullyFusedMLP" if hidden_dim <= 128 else "CutlassMLP",
                    "activation": "ReLU",
                    "output_activation": "Sigmoid",
                    "n_neurons": hidden_dim,
                    "n_hidden_layers": 2,
                },
            )
        else:
            self.net = nn.Sequential(
                nn.Linear(in_dim, hidden_dim),
                nn.ReLU(inplace=True),
                nn.Linear(hidden_dim, hidden_dim),
                nn.ReLU(inplace=True),
                nn.Linear(hidden_dim, 3),
                nn.Sigmoid(),
            )
            # TensoRF starts the last layer's bias at 0 so the initial colour is a neutral grey.
            nn.init.constant_(self.net[-2].bias, 0.0)

    def _inputs(self, features: Float[Tensor, "n f"], directions: Optional[Float[Tensor, "n 3"]]) -> Tensor:
        inputs = [features]
        if self.feature_pe > 0:
            inputs.append(positional_encoding(features, self.feature_pe))
        if self.use_view_dirs:
            if directions is None:
                raise ValueError("this colour MLP was configured with view directions but got none")
            inputs.append(directions)
            if self.view_pe > 0:
                inputs.append(positional_encoding(directions, self.view_pe))
        return torch.cat(inputs, dim=-1)

    def forward(
        self, features: Float[Tensor, "n f"], directions: Optional[Float[Tensor, "n 3"]] = None
    ) -> Float[Tensor, "n 3"]:
        # tinycudann computes in half precision; the rest of the renderer works in float32.
        return self.net(self._inputs(features, directions)).float()

    def forward_bfloat16(
        self, features: Float[Tensor, "n f"], directions: Optional[Float[Tensor, "n 3"]] = None
    ) -> Float[Tensor, "n 3"]:
        """``forward`` (torch layers) with every matrix product in bfloat16 (float32 sums) and the sigmoid in float32:
        a colour within ~2e-3 of ``forward``'s (below 1/255), for rendering without gradients on a CPU that
        multiplies bfloat16 in hardware (``native_bfloat16``). The output layer too: its [n, 128] input in float32
        cost a conversion pass larger than the layer (a fern frame's colours ~0.26 -> ~0.23 s in a throw-away
        timing), and a logit rounded to bfloat16 moves its colour by at most ~1e-3."""
        first, _, second, _, last, _ = self.net
        low = torch.bfloat16
        x = self._inputs(features, directions).to(low)
        x = linear_relu(x, first.weight.to(low), first.bias.to(low))
        x = linear_relu(x, second.weight.to(low), second.bias.to(low))
        return torch.sigmoid(nn.functional.linear(x, last.weight.to(low), last.bias.to(low)).float())


def linear_relu(x: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
    """relu(x W^T + b): on the CPU oneDNN's matrix product with the ReLU applied as it writes (one pass less over
    the [n, hidden] result; a fern frame's 1.39 M rows 0.49-0.56 -> 0.39-0.47 s in a throw-away timing),
    else the two steps. The same numbers either way (the ReLU of the same product). oneDNN has no fused bfloat16
    primitive on a CPU without AVX-512 (it raises when asked for one): there, and for any dtype it refused once,
    the two steps."""
    fused = getattr(torch.ops.mkldnn, "_linear_pointwise", None) if x.device.type == "cpu" else None
    if fused is not None and torch.backends.mkldnn.is_available() and x.dtype not in _NO_FUSED_PRIMITIVE:
        try:
            return fused(x, weight, bias, "relu", [], "")
        except RuntimeError:
            _NO_FUSED_PRIMITIVE.add(x.dtype)
    return torch.relu_(nn.functional.linear(x, weight, bias))


_NO_FUSED_PRIMITIVE: set = set()
"""The dtypes oneDNN could not make a fused linear + ReLU primitive for on this CPU."""
