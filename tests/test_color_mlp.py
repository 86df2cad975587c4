import pytest
import torch

from frugalnerf_ns import color_mlp
from frugalnerf_ns.color_mlp import ColorMLP, choose_implementation, positional_encoding


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


def test_selection_without_tinycudann(monkeypatch):
    monkeypatch.setattr(color_mlp, "tcnn_available", lambda: False)
    assert choose_implementation("auto") == "torch"
    assert choose_implementation("torch") == "torch"
    with pytest.raises(RuntimeError, match="tinycudann is not importable"):
        choose_implementation("tcnn")


def test_selection_with_tinycudann(monkeypatch):
    monkeypatch.setattr(color_mlp, "tcnn_available", lambda: True)
    assert choose_implementation("auto") == "tcnn"
    assert choose_implementation("tcnn") == "tcnn"
    # An explicit torch request always wins (e.g. to compare the two).
    assert choose_implementation("torch") == "torch"


def test_tcnn_available_is_false_without_cuda(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert color_mlp.tcnn_available() is False


def test_tcnn_available_checks_the_import(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)

    def fail(name):
        raise ImportError(name)

    monkeypatch.setattr(color_mlp.importlib, "import_module", fail)
    assert color_mlp.tcnn_available() is False
    monkeypatch.setattr(color_mlp.importlib, "import_module", lambda name: object())
    assert color_mlp.tcnn_available() is True
