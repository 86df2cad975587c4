"""geometry/epipolar.py (the check of scripts/diagnostics/check_dtu_cameras.py): true correspondences lie on their
lines, wrong ones not."""

import torch

from frugalnerf_ns.data.sparse_points import opencv_projection_matrices
from frugalnerf_ns.geometry.epipolar import epipolar_distances, fundamental_from_projections
from frugalnerf_ns.geometry.reprojection import project_to_camera


def test_true_correspondences_lie_on_the_epipolar_lines_and_shifted_ones_do_not():
    torch.manual_seed(0)
    # Two OpenGL cameras 2 units apart, both looking down -z at points around z = -4.
    c2w = torch.eye(4, dtype=torch.float64)[:3].repeat(2, 1, 1)
    c2w[1, 0, 3] = 2.0
    angle = torch.tensor(0.3, dtype=torch.float64)  # the second camera turned towards the first's axis
    c2w[1, 0, 0], c2w[1, 0, 2], c2w[1, 2, 0], c2w[1, 2, 2] = angle.cos(), angle.sin(), -angle.sin(), angle.cos()
    intrinsics = torch.tensor([[300.0, 310.0, 160.0, 120.0]] * 2, dtype=torch.float64)
    points = torch.randn(50, 3, dtype=torch.float64) * 0.5 + torch.tensor([1.0, 0.0, -4.0], dtype=torch.float64)
    pixels = [project_to_camera(points, c2w[i].expand(50, 3, 4), intrinsics[i].expand(50, 4)).pixels for i in range(2)]
    projections = opencv_projection_matrices(c2w, intrinsics)
    f = fundamental_from_projections(projections[0], projections[1], c2w[0, :3, 3])
    assert float(epipolar_distances(f, pixels[0], pixels[1]).max()) < 1e-6
    # Pixels moved across the lines (a wrong principal point, say) are off by about the shift.
    shifted = pixels[1] + torch.tensor([0.0, 5.0], dtype=torch.float64)
    assert float(epipolar_distances(f, pixels[0], shifted).median()) > 2.0
