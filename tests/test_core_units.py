"""Small core units: Gaussians transforms and SH, restricted unpickling, scene validation,
hold-out split, LiDAR projection."""
import os
import pickle

import numpy as np
import pytest
import torch

from omnire.data.scene import SceneDataError, holdout_split
from omnire.gaussians import Gaussians, eval_sh, num_sh_bases, rgb_to_sh0
from omnire.geometry import quat_multiply, quat_to_rotmat, rotmat_to_quat
from omnire.io import safe_pickle
from omnire.lidar import project_points


def random_gaussians(n, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    return Gaussians(torch.randn(n, 3, generator=g, dtype=torch.float64), torch.randn(n, 4, generator=g, dtype=torch.float64),
                     torch.randn(n, 3, generator=g, dtype=torch.float64), torch.randn(n, generator=g, dtype=torch.float64),
                     torch.randn(n, 1, 3, generator=g, dtype=torch.float64),
                     torch.randn(n, num_sh_bases(degree) - 1, 3, generator=g, dtype=torch.float64))


def covariance(g: Gaussians) -> torch.Tensor:
    R = quat_to_rotmat(g.quats)
    S = torch.diag_embed(torch.exp(g.scales))
    return R @ S @ S @ R.transpose(1, 2)


def test_transform_rotates_means_and_covariances():
    g = random_gaussians(7)
    R = quat_to_rotmat(torch.tensor([0.3, -0.2, 0.9, 0.1], dtype=torch.float64))
    t = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64)
    h = g.transform(R, t)
    torch.testing.assert_close(h.means, g.means @ R.T + t)
    torch.testing.assert_close(covariance(h), R @ covariance(g) @ R.T)
    # the shared rotation's matrix form of the quaternion product is the Hamilton product
    torch.testing.assert_close(h.quats, quat_multiply(rotmat_to_quat(R)[None].expand(7, 4), g.quats))
    # per-Gaussian rotations
    Rs = quat_to_rotmat(torch.randn(7, 4, dtype=torch.float64))
    h = g.transform(Rs, t.expand(7, 3))
    torch.testing.assert_close(covariance(h), Rs @ covariance(g) @ Rs.transpose(1, 2))
    torch.testing.assert_close(quat_to_rotmat(rotmat_to_quat(Rs)), Rs)


def test_cat_pads_sh_bands():
    a, b = random_gaussians(3, degree=3), random_gaussians(2, degree=1)
    c = Gaussians.cat([a, b])
    assert len(c) == 5 and c.shN.shape == (5, 15, 3)
    assert torch.count_nonzero(c.shN[3:, 3:]) == 0


def test_sh_degree0_is_colour_and_bands_are_orthonormal():
    rgb = torch.rand(4, 3, dtype=torch.float64)
    coeffs = rgb_to_sh0(rgb)
    dirs = torch.nn.functional.normalize(torch.randn(4, 3, dtype=torch.float64), dim=-1)
    torch.testing.assert_close(eval_sh(0, coeffs, dirs) + 0.5, rgb)
    # Monte Carlo orthonormality of the 16 real SH basis functions over the sphere
    n = 200_000
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1)
    basis = torch.stack([eval_sh(3, torch.eye(16, dtype=torch.float64)[i].reshape(1, 16, 1).expand(n, 16, 1), d)[:, 0]
                         for i in range(16)], 1)
    gram = basis.T @ basis * (4 * np.pi / n)
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)


class _Evil:
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def test_restricted_unpickler_refuses_code(tmp_path):
    p = tmp_path / "evil.pkl"
    p.write_bytes(pickle.dumps(_Evil()))
    with pytest.raises(safe_pickle.UnsafePickleError, match="evil.pkl.*system"):
        safe_pickle.load(p)
    ok = tmp_path / "ok.pkl"
    ok.write_bytes(pickle.dumps({"a": np.arange(3), "b": [1.5, "x"]}))
    out = safe_pickle.load(ok)
    assert out["a"].tolist() == [0, 1, 2] and out["b"] == [1.5, "x"]
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(b"\x80\x04garbage")
    with pytest.raises(pickle.UnpicklingError, match="bad.pkl"):
        safe_pickle.load(bad)


def test_gzip_bomb_refused_before_expanding(tmp_path):
    # 64 MB of zeros compress to ~64 KB; a reader that allows 8 MB must refuse it while
    # inflating, without holding the expanded bytes (the cap is checked per 1 MB chunk).
    import gzip
    import resource

    p = tmp_path / "bomb.pkl.gz"
    p.write_bytes(gzip.compress(pickle.dumps(np.zeros(8 * 2**20)), compresslevel=9))
    assert p.stat().st_size < 1 << 20
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    with pytest.raises(safe_pickle.PickleReadError, match="bomb.pkl.gz.*expands to more than"):
        safe_pickle.load(p, max_bytes=8 * 2**20)
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - before < 48 * 1024  # KB: not 64 MB
    assert safe_pickle.load(p, max_bytes=80 * 2**20).shape == (8 * 2**20,)


def test_allowlist_is_the_readers_choice(tmp_path):
    import collections

    p = tmp_path / "counter.pkl"
    p.write_bytes(pickle.dumps(collections.Counter("aab")))
    with pytest.raises(safe_pickle.UnsafePickleError, match="refused as unsafe.*collections.Counter"):
        safe_pickle.load(p)
    extended = safe_pickle.NUMPY_DATA | safe_pickle.PickleAllowlist(frozenset({("collections", "Counter")}))
    assert safe_pickle.load(p, extended) == {"a": 2, "b": 1}


def test_holdout_split_matches_paper():
    train, test = holdout_split(35, 10)
    assert test.tolist() == [10, 20, 30] and len(train) == 32
    assert len(holdout_split(5, 0)[1]) == 0


def test_scene_validation_names_the_field(tiny_scene):
    tiny_scene.tracks[0].poses[1, 0, 3] = np.nan
    with pytest.raises(SceneDataError, match="car-1.*poses"):
        tiny_scene.validate()
    tiny_scene.tracks[0].poses[1, 0, 3] = 0
    tiny_scene.cameras[0].intrinsics = np.eye(4)
    with pytest.raises(SceneDataError, match="cam0.*intrinsics.*expected \\(3, 3\\)"):
        tiny_scene.validate()


def test_lidar_projection_brute_force():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-5, -5, 1], [5, 5, 20], size=(500, 3))
    K = np.array([[50.0, 0, 20], [0, 50.0, 15], [0, 0, 1]])
    idx, z = project_points(pts, np.eye(4), K, 40, 30)
    best = {}
    for p in pts:
        u, v = int(np.floor(50 * p[0] / p[2] + 20)), int(np.floor(50 * p[1] / p[2] + 15))
        if 0 <= u < 40 and 0 <= v < 30 and p[2] > 0.5:
            k = v * 40 + u
            best[k] = min(best.get(k, np.inf), p[2])
    assert dict(zip(idx.tolist(), z.tolist())) == pytest.approx(best)


def test_background_init_drops_the_recording_vehicles_own_lidar_returns(tmp_path):
    """Returns within ``ego_clearance`` of one of their frame's cameras (the vehicle's roof and
    camera mounts) seed no background Gaussian; every other point is kept (brute force)."""
    import numpy as np

    from scene_helpers import make_tiny_scene
    from omnire.nodes.background import lidar_points_for_init

    scene = make_tiny_scene(tmp_path)
    rng = np.random.default_rng(1)
    frames = [f for f in scene.train_frames if scene.lidar.points[int(f)] is not None]
    scene_pts = {int(f): scene.lidar.points[int(f)].copy() for f in frames}
    for f in frames:  # returns off the vehicle: within 0.2-1.2 m of the frame's cameras
        centres = np.stack([c.cam_to_world[int(f), :3, 3] for c in scene.cameras])
        d = rng.normal(size=(40, 3))
        d *= rng.uniform(0.2, 1.2, (40, 1)) / np.linalg.norm(d, axis=1, keepdims=True)
        own = centres[rng.integers(0, len(centres), 40)] + d
        scene.lidar.points[int(f)] = np.concatenate([scene_pts[int(f)], own]).astype(np.float32)
    kept = lidar_points_for_init(scene, np.array(frames), [], ego_clearance=1.5)
    expected = []
    for f in frames:
        pts = scene.lidar.points[int(f)]
        centres = np.stack([c.cam_to_world[int(f), :3, 3] for c in scene.cameras])
        far = np.array([min(np.linalg.norm(p - c) for c in centres) >= 1.5 for p in pts])
        expected.append(pts[far])
    np.testing.assert_array_equal(kept, np.concatenate(expected))
    assert len(kept) == sum(len(p) for p in scene_pts.values())  # the scene's own points all stay
    everything = lidar_points_for_init(scene, np.array(frames), [], ego_clearance=0.0)
    assert len(everything) == len(kept) + 40 * len(frames)


def test_rotmat_to_quat_matches_kornia_on_every_branch_with_gradients():
    """The lean Shepperd conversion gives kornia's quaternions (sign made w >= 0) and their
    gradients, on rotations that take each of the four branches."""
    from kornia.geometry.conversions import rotation_matrix_to_quaternion

    from omnire.geometry import axis_angle_to_rotmat

    g = torch.Generator().manual_seed(4)
    axes = torch.nn.functional.normalize(torch.randn(400, 3, generator=g, dtype=torch.float64), dim=-1)
    angles = torch.rand(400, 1, generator=g, dtype=torch.float64) * np.pi
    angles[:100] = np.pi - 1e-3 * angles[:100]  # near half turns: trace near -1, the x/y/z branches
    special = torch.tensor([[np.pi, 0, 0], [0, np.pi, 0], [0, 0, np.pi], [0, 0, 0], [1e-9, 0, 0]], dtype=torch.float64)
    R = axis_angle_to_rotmat(torch.cat([axes * angles, special])).requires_grad_(True)
    ref_R = R.detach().clone().requires_grad_(True)
    diag = torch.diagonal(R.detach(), dim1=-2, dim2=-1)
    branches = torch.where(diag.sum(-1) > 0, 0, 1 + diag.argmax(-1))
    assert set(branches.tolist()) == {0, 1, 2, 3}
    q = rotmat_to_quat(R)
    ref = rotation_matrix_to_quaternion(ref_R)
    ref = torch.where(ref[:, :1] < 0, -ref, ref)
    torch.testing.assert_close(q, ref, rtol=0, atol=1e-14)
    w = torch.randn(q.shape, generator=g, dtype=torch.float64)
    (q * w).sum().backward()
    (ref * w).sum().backward()
    torch.testing.assert_close(R.grad, ref_R.grad, rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(rotmat_to_quat, (R.detach()[:8].clone().requires_grad_(True),))
    # numpy in, numpy out; batch shape kept; NaN passes through
    assert rotmat_to_quat(np.eye(3)).tolist() == [1.0, 0.0, 0.0, 0.0]
    assert rotmat_to_quat(R.detach().reshape(5, 81, 3, 3)).shape == (5, 81, 4)
    assert bool(torch.isnan(rotmat_to_quat(torch.full((3, 3), float("nan")))).all())


def test_quat_to_se3_against_scipy():
    """A point mapped by the 4x4 is scipy's rotation (scalar-last quaternion) plus the translation,
    for batches and for quaternions of any norm (normalised, as quat_to_rotmat does)."""
    from scipy.spatial.transform import Rotation

    from omnire.geometry import quat_to_se3

    rng = np.random.default_rng(5)
    q, t, p = rng.normal(size=(9, 4)), rng.normal(size=(9, 3)), rng.normal(size=(9, 3))
    T = quat_to_se3(q, t)
    assert T.shape == (9, 4, 4) and T.dtype == np.float64 and np.array_equal(T[:, 3], np.tile([0, 0, 0, 1.0], (9, 1)))
    expected = Rotation.from_quat(q[:, [1, 2, 3, 0]]).apply(p) + t
    assert np.allclose(np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3], expected, atol=1e-12)
    single = quat_to_se3(np.array([1.0, 0.0, 0.0, 0.0]), np.array([1.0, 2.0, 3.0]))
    assert np.array_equal(single[:3, :3], np.eye(3)) and single[:3, 3].tolist() == [1.0, 2.0, 3.0]
