"""Body template loading (shipped Anny-derived npz, SMPL pickles) and numpy LBS."""
from __future__ import annotations

import io
import pickle

import numpy as np
import pytest

from omnire.geometry import axis_angle_to_rotmat
from omnire_body import SMPL_PARENTS, BodyTemplateError, forward_kinematics, lbs, load_anny_template, load_smpl_pickle, load_template
from omnire_body.template import ANNY_TEMPLATE, SMPL_PICKLE
from omnire.io import safe_pickle
from omnire.io.safe_pickle import UnsafePickleError

I3 = np.eye(3)


def rest_pose(batch: int | None = None):
    go, bp = I3.copy(), np.tile(I3, (23, 1, 1))
    if batch is None:
        return go, bp
    return np.tile(go, (batch, 1, 1)), np.tile(bp, (batch, 1, 1, 1))


def test_shipped_template_is_in_smpl_canonical_frame():
    assert ANNY_TEMPLATE.is_file(), "the template must ship inside omnire/body/assets"
    t = load_template()
    assert t.vertices.shape == (13718, 3) and t.faces.shape == (27420, 3)
    assert t.joints.shape == (24, 3) and t.weights.shape == (13718, 24)
    np.testing.assert_array_equal(t.parents, SMPL_PARENTS)
    np.testing.assert_allclose(t.weights.sum(1), 1.0, atol=1e-5)
    # y up: head above pelvis above ankles; height about 1.63 m.
    head, pelvis, l_ankle = t.joints[15], t.joints[0], t.joints[7]
    assert head[1] > pelvis[1] > l_ankle[1]
    assert 1.55 < np.ptp(t.vertices[:, 1]) < 1.7
    # x = body's left: the left hip/shoulder have positive x.
    assert t.joints[1, 0] > 0 and t.joints[16, 0] > 0 and t.joints[2, 0] < 0
    # z forward: the toes (feet joints) point forward of the ankles.
    assert t.joints[10, 2] > t.joints[7, 2]


def test_rest_pose_returns_template():
    t = load_template()
    out = lbs(t, *rest_pose())
    np.testing.assert_allclose(out.vertices, t.vertices, atol=1e-6)
    np.testing.assert_allclose(out.joints, t.joints, atol=1e-12)


def test_forward_kinematics_chain():
    t = load_template()
    go, bp = rest_pose()
    R_hip = axis_angle_to_rotmat(np.array([-0.6, 0.0, 0.2]))
    R_knee = axis_angle_to_rotmat(np.array([0.9, 0.0, 0.0]))
    bp[0] = R_hip  # left_hip (joint 1)
    bp[3] = R_knee  # left_knee (joint 4)
    joints, A = forward_kinematics(t.joints, t.parents, go, bp)
    J = t.joints
    knee = J[1] + R_hip @ (J[4] - J[1])
    ankle = knee + R_hip @ R_knee @ (J[7] - J[4])
    np.testing.assert_allclose(joints[4], knee, atol=1e-12)
    np.testing.assert_allclose(joints[7], ankle, atol=1e-12)
    # Untouched right leg stays.
    np.testing.assert_allclose(joints[[2, 5, 8]], J[[2, 5, 8]], atol=1e-12)
    # Skinning transform maps the rest joint to its posed position.
    np.testing.assert_allclose(A[7, :3, :3] @ J[7] + A[7, :3, 3], ankle, atol=1e-12)


def test_global_orient_turns_about_pelvis_and_transl_moves():
    t = load_template()
    R = axis_angle_to_rotmat(np.array([0.0, 1.1, 0.0]))
    go, bp = rest_pose()
    out = lbs(t, R, bp, transl=np.array([1.0, 2.0, 3.0]))
    expect = (t.vertices - t.joints[0]) @ R.T + t.joints[0] + [1.0, 2.0, 3.0]
    np.testing.assert_allclose(out.vertices, expect, atol=1e-6)


def test_only_skinned_vertices_move_and_batch_matches_single():
    t = load_template()
    go, bp = rest_pose()
    bp[4] = axis_angle_to_rotmat(np.array([1.0, 0.0, 0.0]))  # right_knee (joint 5)
    out = lbs(t, go, bp)
    moved = np.linalg.norm(out.vertices - t.vertices, axis=1) > 1e-6
    leg = t.weights[:, [5, 8, 11]].sum(1) > 1e-6
    assert moved.any()
    assert not (moved & ~leg).any()
    gob, bpb = rest_pose(3)
    bpb[1] = bp
    outb = lbs(t, gob, bpb)
    np.testing.assert_allclose(outb.vertices[1], out.vertices, atol=1e-12)
    np.testing.assert_allclose(outb.vertices[0], t.vertices, atol=1e-6)


def _fake_smpl(V: int = 30, rng=np.random.default_rng(0)):
    verts = rng.normal(size=(V, 3))
    weights = rng.random((V, 24))
    weights /= weights.sum(1, keepdims=True)
    reg = rng.random((24, V))
    reg /= reg.sum(1, keepdims=True)
    kintree = np.stack([np.where(SMPL_PARENTS < 0, 4294967295, SMPL_PARENTS), np.arange(24)])
    return {
        "v_template": verts, "weights": weights, "J_regressor": reg, "kintree_table": kintree,
        "shapedirs": rng.normal(size=(V, 3, 10)) * 0.01, "posedirs": rng.normal(size=(V, 3, 207)) * 0.01,
        "f": rng.integers(0, V, size=(40, 3)).astype(np.uint32),
    }


def test_smpl_pickle_loads_with_blend_shapes(tmp_path):
    d = _fake_smpl()
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    path.write_bytes(pickle.dumps(d, protocol=4))
    t = load_smpl_pickle(path)
    assert t.parents[0] == -1
    np.testing.assert_allclose(t.joints, d["J_regressor"] @ d["v_template"])
    betas = np.linspace(-1, 1, 10)
    go, bp = rest_pose()
    out = lbs(t, go, bp, betas=betas)
    shaped = d["v_template"] + d["shapedirs"] @ betas
    np.testing.assert_allclose(out.vertices, shaped, atol=1e-9)  # rest pose: no pose blend
    bp[0] = axis_angle_to_rotmat(np.array([0.3, 0.0, 0.0]))
    with_blend = lbs(t, go, bp).vertices
    without = lbs(t, go, bp, pose_blend=False).vertices
    assert np.abs(with_blend - without).max() > 1e-4


def test_bad_templates_are_refused(tmp_path):
    d = _fake_smpl()
    d["weights"] = d["weights"][:, :20]
    path = tmp_path / "bad.pkl"
    path.write_bytes(pickle.dumps(d))
    with pytest.raises(BodyTemplateError, match="bad.pkl.*weights"):
        load_smpl_pickle(path)

    class Evil:
        def __reduce__(self):
            import os
            return (os.system, ("true",))

    evil = tmp_path / "evil.pkl"
    evil.write_bytes(pickle.dumps({"v_template": Evil()}))
    with pytest.raises(UnsafePickleError, match="evil.pkl"):
        load_smpl_pickle(evil)
    with pytest.raises(FileNotFoundError, match="nope.npz"):
        load_anny_template(tmp_path / "nope.npz")


def test_chumpy_and_sparse_standins(tmp_path):
    """SMPL pickles made with chumpy/scipy: build such a pickle by hand (no chumpy needed)."""
    class Ch:  # stands for chumpy.ch.Ch in the stream
        pass

    Ch.__module__, Ch.__qualname__ = "chumpy.ch", "Ch"
    obj = Ch.__new__(Ch)
    obj.__dict__ = {"x": np.ones((2, 3))}
    buf = io.BytesIO()

    class P(pickle.Pickler):
        def reducer_override(self, o):
            if isinstance(o, Ch):
                return (Ch, (), o.__dict__)
            return NotImplemented

    import sys
    import types

    fake, parent = types.ModuleType("chumpy.ch"), types.ModuleType("chumpy")
    fake.Ch, parent.ch = Ch, fake
    sys.modules.update({"chumpy": parent, "chumpy.ch": fake})
    try:
        P(buf, protocol=2).dump({"shapedirs": obj})
    finally:
        del sys.modules["chumpy.ch"], sys.modules["chumpy"]
    p = tmp_path / "smpl.pkl"
    p.write_bytes(buf.getvalue())
    out = safe_pickle.load(p, SMPL_PICKLE)
    assert isinstance(out["shapedirs"], np.ndarray) and out["shapedirs"].shape == (2, 3)
