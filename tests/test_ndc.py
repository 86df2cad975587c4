import torch

from frugalnerf_ns.geometry.ndc import metric_distance_from_ndc, point_to_ndc, rays_to_ndc

FOCAL, W, H = 400.0, 504.0, 378.0


def camera_rays(n=50, seed=0):
    """Rays from cameras near the origin looking down -z, through pixels inside the image."""
    gen = torch.Generator().manual_seed(seed)
    origins = (torch.rand(n, 3, generator=gen) - 0.5) * 0.2
    u = torch.rand(n, generator=gen) * W
    v = torch.rand(n, generator=gen) * H
    dirs = torch.stack([(u - W / 2) / FOCAL, -(v - H / 2) / FOCAL, -torch.ones(n)], dim=-1)
    return origins, torch.nn.functional.normalize(dirs, dim=-1)


def test_rays_start_on_the_ndc_near_plane_inside_the_box():
    origins, dirs = camera_rays()
    rays = rays_to_ndc(origins, dirs, FOCAL, W, H, near=1.0)
    assert torch.allclose(rays.origins[:, 2], torch.full((50,), -1.0), atol=1e-5)
    # Rays through the image from near the NDC camera start within TensoRF's NDC box.
    assert (rays.origins[:, 0].abs() <= 1.5).all() and (rays.origins[:, 1].abs() <= 1.67).all()
    assert torch.allclose(rays.directions.norm(dim=-1), torch.ones(50), atol=1e-6)
    assert (rays.directions[:, 2] > 0).all()


def test_metric_distance_recovered_from_ndc_matches_the_true_distance():
    origins, dirs = camera_rays()
    true_distance = torch.linspace(2.0, 40.0, 50)
    points = origins + dirs * true_distance[:, None]
    rays = rays_to_ndc(origins, dirs, FOCAL, W, H, near=1.0)
    ndc_points = point_to_ndc(points, FOCAL, W, H, near=1.0)
    # The NDC point lies on the NDC ray ...
    ndc_distance = ((ndc_points - rays.origins) * rays.directions).sum(-1)
    on_ray = rays.origins + rays.directions * ndc_distance[:, None]
    assert torch.allclose(on_ray, ndc_points, atol=1e-4)
    # ... and converting its NDC distance back gives the metric distance along the world ray.
    recovered = metric_distance_from_ndc(ndc_distance, rays, near=1.0)
    assert torch.allclose(recovered, true_distance, rtol=1e-3)


def test_far_points_stay_finite_and_grazing_rays_do_not_blow_up():
    origins, dirs = camera_rays(4)
    rays = rays_to_ndc(origins, dirs, FOCAL, W, H)
    far = metric_distance_from_ndc(rays.ndc_length * 1.0, rays)  # t' = 1: infinitely far
    assert torch.isfinite(far).all() and (far > 100).all()
    sideways = torch.tensor([[1.0, 0.0, 0.0]])
    grazing = rays_to_ndc(torch.zeros(1, 3), sideways, FOCAL, W, H)
    assert torch.isfinite(grazing.origins).all() and torch.isfinite(grazing.directions).all()
