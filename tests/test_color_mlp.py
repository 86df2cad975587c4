import pytest
import torch

from frugalnerf_ns.field import color_mlp
from frugalnerf_ns.field.color_mlp import ColorMLP, positional_encoding


def test_positional_encoding_shape_and_values():
    x = torch.tensor([[0.0, 0.5]])
    enc = positional_encoding(x, 2)
    assert enc.shape == (1, 8)
    # sin(0), sin(0), sin(0.5), sin(1.0), then the cosines
    assert torch.allclose(enc[0, :4], torch.sin(torch.tensor([0.0, 0.0, 0.5, 1.0])))
    assert positional_encoding(x, 0).shape == (1, 0)


def test_torch_mlp_outputs_colours_with_gradients():
    mlp = ColorMLP(27, hidden_dim=32, feature_pe=2, use_view_dirs=True, view_pe=2, implementation="torch")
    assert mlp.implementation == "torch" and mlp.in_dim == 27 + 4 * 27 + 3 + 12
    features = torch.randn(50, 27, requires_grad=True)
    rgb = mlp(features, torch.nn.functional.normalize(torch.randn(50, 3), dim=-1))
    assert rgb.shape == (50, 3) and rgb.dtype == torch.float32
    assert (rgb > 0).all() and (rgb < 1).all()
    rgb.sum().backward()
    assert features.grad.abs().sum() > 0
    assert all(p.grad is not None for p in mlp.parameters())
    with pytest.raises(ValueError, match="view directions"):
        mlp(features)


HAS_TCNN = color_mlp.tcnn_available()  # the real check: tinycudann importable and a CUDA device present


@pytest.mark.skipif(HAS_TCNN, reason="this machine can run tinycudann")
def test_auto_builds_the_torch_mlp_where_tinycudann_cannot_run():
    auto = ColorMLP(27, hidden_dim=16, implementation="auto")
    assert auto.implementation == "torch"
    assert [type(m).__name__ for m in auto.net] == ["Linear", "ReLU", "Linear", "ReLU", "Linear", "Sigmoid"]
    # The same network as an explicit torch request: same parameters give the same colours.
    explicit = ColorMLP(27, hidden_dim=16, implementation="torch")
    explicit.load_state_dict(auto.state_dict())
    features = torch.randn(8, 27)
    assert torch.equal(auto(features), explicit(features))


@pytest.mark.skipif(HAS_TCNN, reason="this machine can run tinycudann")
def test_asking_for_tinycudann_where_it_cannot_run_is_an_option_error():
    with pytest.raises(RuntimeError, match="tinycudann is not importable"):
        ColorMLP(27, implementation="tcnn")
    from frugalnerf_ns.run.options import OptionError, validate_options
    from frugalnerf_ns.run.presets import build_trainer_config

    config = build_trainer_config("frugalnerf")
    config.pipeline.model.mlp_implementation = "tcnn"
    with pytest.raises(OptionError, match="--pipeline.model.mlp-implementation must be auto or torch"):
        validate_options(config)


@pytest.mark.skipif(not HAS_TCNN, reason="needs tinycudann and a CUDA device")
def test_auto_builds_tinycudann_where_it_can_run():
    mlp = ColorMLP(27, hidden_dim=64, implementation="auto").cuda()
    assert mlp.implementation == "tcnn" and type(mlp.net).__module__.startswith("tinycudann")
    rgb = mlp(torch.randn(128, 27, device="cuda"))
    assert rgb.dtype == torch.float32 and ((rgb >= 0) & (rgb <= 1)).all()
