"""Optional monocular depth (L_d): Pearson loss, local-only model loading, caching, datamanager and model."""

import pytest
import torch

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.model.losses import pearson_depth_loss, per_view_pearson_loss
from frugalnerf_ns.data.mono_depth import load_depth_model, load_or_predict

transformers = pytest.importorskip("transformers")


@pytest.fixture(scope="module")
def tiny_depth_model(tmp_path_factory):
    """A randomly initialised DPT of the real architecture, saved locally (nothing is downloaded)."""
    config = transformers.DPTConfig(
        hidden_size=32, num_hidden_layers=4, num_attention_heads=2, intermediate_size=64, image_size=64,
        patch_size=16, neck_hidden_sizes=[8, 16, 32, 32], fusion_hidden_size=16, backbone_out_indices=[0, 1, 2, 3],
    )
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("dpt")
    transformers.DPTForDepthEstimation(config).save_pretrained(path)
    return path


def test_pearson_loss_zero_when_correlated_two_when_anticorrelated():
    x = torch.linspace(1.0, 5.0, 50)
    assert float(pearson_depth_loss(3.0 * x + 2.0, x)) == pytest.approx(0.0, abs=1e-6)
    assert float(pearson_depth_loss(-x, x)) == pytest.approx(2.0, abs=1e-6)
    # Too few rays or a constant prediction: no signal, no NaN.
    assert float(pearson_depth_loss(x[:1], x[:1])) == 0.0
    assert float(pearson_depth_loss(x, torch.ones(50))) == 0.0


def test_pearson_gradient_moves_the_render_towards_the_prediction():
    torch.manual_seed(0)
    predicted = torch.rand(100)
    rendered = (predicted + 0.5 * torch.rand(100)).requires_grad_(True)
    loss = pearson_depth_loss(rendered, predicted)
    loss.backward()
    assert torch.isfinite(rendered.grad).all()
    stepped = pearson_depth_loss(rendered.detach() - 0.1 * rendered.grad, predicted)
    assert float(stepped) < float(loss.detach())


def test_per_view_loss_ignores_each_views_scale_and_shift():
    x = torch.linspace(1.0, 2.0, 20)
    rendered = torch.cat([x, x])
    predicted = torch.cat([10 * x - 3, 0.1 * x + 7])  # two views, two unrelated affine maps
    view = torch.cat([torch.zeros(20), torch.ones(20)]).long()
    assert float(per_view_pearson_loss(rendered, predicted, view)) == pytest.approx(0.0, abs=1e-6)
    assert float(pearson_depth_loss(rendered, predicted)) > 0.1  # pooled, the views disagree


def test_missing_or_wrong_model_folder_is_a_clear_error(tmp_path):
    with pytest.raises(DataError, match="mono-depth-model .*no such folder"):
        load_depth_model(tmp_path / "absent")
    with pytest.raises(DataError, match="no config.json"):
        load_depth_model(tmp_path)


def test_predictions_have_the_image_size_and_are_cached(tiny_depth_model, tmp_path):
    images = torch.rand(2, 24, 40, 3)
    cache = tmp_path / "mono.npz"
    depth = load_or_predict(tiny_depth_model, images, cache, disparity=True, input_size=64)
    assert depth.shape == (2, 24, 40) and torch.isfinite(depth).all() and cache.exists()
    # The cache answers without the model: a missing folder would fail if it were loaded again.
    moved = tiny_depth_model.parent / "moved"
    tiny_depth_model.rename(moved)
    try:
        with pytest.raises(DataError):
            load_or_predict(tiny_depth_model, images, cache, disparity=True, input_size=64)  # key names the folder
        again = load_or_predict(moved, images, tmp_path / "other.npz", disparity=True, input_size=64)
        assert torch.allclose(again, depth, atol=1e-5)
        assert torch.equal(load_or_predict(moved, images, tmp_path / "other.npz", True, 64), again)
    finally:
        moved.rename(tiny_depth_model)


def test_datamanager_and_model_add_the_mono_depth_term(procedural_scene, tiny_depth_model, tmp_path):
    from frugalnerf_ns.model.frugalnerf import FrugalNeRFModelConfig
    from tests.helpers import manager_for

    manager = manager_for(
        procedural_scene, mono_depth_model=tiny_depth_model, mono_depth_input_size=64, sparse_cache_dir=tmp_path
    )
    bundle, batch = manager.next_train(0)
    idx = batch.indices
    assert torch.equal(batch.mono_depth, manager.mono_depth[idx[:, 0], idx[:, 1], idx[:, 2]])
    config = FrugalNeRFModelConfig(
        initial_voxels=16**3, final_voxels=16**3, upsample_at=(), alpha_mask_at=(), density_components=(4, 2, 2),
        appearance_components=(8, 2, 2), mlp_hidden_dim=16, background="white", density_activation="softplus",
    )
    model = config.setup(scene_box=manager.train_dataset.scene_box, num_train_data=len(manager.train_dataset), metadata={})
    model.train()
    outputs = model(bundle)
    loss = model.get_loss_dict(outputs, batch, model.get_metrics_dict(outputs, batch))
    assert "mono_depth" in loss and 0.0 <= float(loss["mono_depth"].detach()) <= 3 * 2 * 0.01 + 1e-6
    loss["mono_depth"].backward()
    assert any(p.grad is not None and torch.isfinite(p.grad).all() for p in model.field.grid_parameters())
    model.config.mono_depth_weight = 0.0
    assert "mono_depth" not in model.get_loss_dict(model(bundle), batch, None)
