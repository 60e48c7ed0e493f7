"""Frustum test of omnire.camera against brute force: projection for margin 0, distances to
a densely sampled frustum for margins > 0."""
import numpy as np
import pytest
import torch
from scipy.spatial import cKDTree

from omnire.camera import Camera, in_frustum


def make_camera(seed=0):
    rng = np.random.default_rng(seed)
    # A rotated, translated camera with an off-centre principal point.
    a = rng.normal(size=3)
    R = torch.linalg.matrix_exp(torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64))
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = R
    T[:3, 3] = torch.tensor(rng.normal(size=3) * 5)
    K = torch.tensor([[200.0, 0, 70.0], [0, 180.0, 40.0], [0, 0, 1]], dtype=torch.float64)
    return Camera(K, T, 160, 90)


def camera_coords(points, cam):
    R, c = cam.cam_to_world[:3, :3], cam.cam_to_world[:3, 3]
    return (points - c) @ R


def test_margin_zero_is_projection_inside_the_image():
    cam = make_camera()
    pts = torch.randn(20000, 3, dtype=torch.float64) * 15 + cam.cam_to_world[:3, 3]
    p = camera_coords(pts, cam)
    uv = p @ cam.K.T
    u, v = uv[:, 0] / p[:, 2], uv[:, 1] / p[:, 2]
    inside = (p[:, 2] > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
    assert 0 < int(inside.sum()) < len(pts)
    assert torch.equal(in_frustum(pts, cam, 0.0), inside)


def frustum_samples(cam, depth=40.0, n=60):
    """Dense world points on the frustum (up to ``depth``): the pyramid's faces and interior."""
    s = torch.linspace(0, 1, n, dtype=torch.float64)
    u, v, z = torch.meshgrid(s * cam.width, s * cam.height, s * depth, indexing="ij")
    u, v, z = u.reshape(-1), v.reshape(-1), z.reshape(-1)
    K = cam.K
    p = torch.stack([(u - K[0, 2]) / K[0, 0] * z, (v - K[1, 2]) / K[1, 1] * z, z], -1)
    return p @ cam.cam_to_world[:3, :3].T + cam.cam_to_world[:3, 3]


@pytest.mark.parametrize("margin", [0.5, 2.0])
def test_margin_keeps_every_point_near_the_frustum(margin):
    cam = make_camera(1)
    dense = frustum_samples(cam)
    # Points at distance < margin from the frustum: frustum samples moved by random vectors.
    g = torch.Generator().manual_seed(0)
    idx = torch.randint(0, len(dense), (5000,), generator=g)
    d = torch.randn(5000, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True) * torch.rand(5000, 1, generator=g, dtype=torch.float64) * margin * 0.999
    near = dense[idx] + d
    near_local = camera_coords(near, cam)
    near = near[near_local[:, 2] < 35]  # away from the sampled depth limit
    assert bool(in_frustum(near, cam, margin).all())
    # Points far (> 2 margin) from every frustum sample are dropped.
    pts = torch.randn(4000, 3, dtype=torch.float64) * 12 + cam.cam_to_world[:3, 3]
    pts = pts[camera_coords(pts, cam)[:, 2] < 30]
    # exact nearest-sample distances by a k-d tree (a cdist to all 216,000 samples took 10-16 s)
    dist = torch.from_numpy(cKDTree(dense.numpy()).query(pts.numpy())[0])
    far = dist > 2 * margin + 0.5  # 0.5: spacing of the dense samples
    assert int(far.sum()) > 100
    assert not bool(in_frustum(pts[far], cam, margin).any())


def test_bad_input_is_refused():
    cam = make_camera()
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        in_frustum(torch.zeros(5, 2), cam, 1.0)
    with pytest.raises(ValueError, match="margin"):
        in_frustum(torch.zeros(5, 3), cam, -1.0)
    with pytest.raises(ValueError, match="image size"):
        Camera(cam.K, cam.cam_to_world, 0, 10)


def test_per_point_margin_equals_scalar_margin_point_by_point():
    cam = make_camera(2)
    pts = torch.randn(400, 3, dtype=torch.float64) * 15 + cam.cam_to_world[:3, 3]
    margins = torch.rand(400, dtype=torch.float64) * 4
    per_point = in_frustum(pts, cam, margins)
    one_by_one = torch.cat([in_frustum(pts[i:i + 1], cam, float(margins[i])) for i in range(400)])
    assert torch.equal(per_point, one_by_one)
    with pytest.raises(ValueError, match="per-point margin"):
        in_frustum(pts, cam, margins[:5])
