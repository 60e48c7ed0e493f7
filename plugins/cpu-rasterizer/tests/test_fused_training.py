"""The fused training path (``CpuRasterizer.rasterize_gaussians_train``: raw Gaussians in
parts, activation, SH colour, off-screen rejection, rasterization and the backward to every
raw tensor in the kernel) against the obvious torch composition it replaces: activate in
torch, ``Gaussians.cat`` + ``Gaussians.colors``, then :meth:`CpuRasterizer.rasterize`.

float64 runs the double-precision kernel on both sides, so pixels, gradients, AbsGrad and
radii must agree to rounding (1e-9 relative); float32 to float rounding (1e-4 relative for
gradients, whose sums run in a different order). ``torch.autograd.gradcheck`` checks the
fused backward against central differences on a tiny scene.
"""
from __future__ import annotations

import math

import pytest
import torch
from omnire_rasterizer_cpu import available

OK, REASON = available("cpu")
if not OK:
    pytest.skip(f"cpu rasterizer extension unavailable: {REASON}", allow_module_level=True)

from omnire_rasterizer_cpu.rasterizer import CpuRasterizer
from omnire_rasterizer_cpu.testing import random_scene

from omnire.camera import Camera
from omnire.gaussians import GAUSSIAN_KEYS, Gaussians
from omnire.rasterization import RasterInputError, RasterSettings, Splats

W, H = 80, 56


def raw_parts(seed: int, dtype, degrees=(3, 1, 0, 2), n=150, width=W, height=H, opacity=(0.02, 0.95),
              scale_px=3.0, depth=(2.0, 8.0), scatter=True):
    """Parts of raw Gaussians, one SH degree each: many in view, some scattered (behind or
    beside the camera, rejected by the culling), then a part entirely behind the camera and
    an empty one. Returns (parts, camera)."""
    parts = []
    for k, deg in enumerate(degrees):
        s = random_scene(n, width, height, seed=seed + k, dtype=dtype, scale_px=scale_px, opacity=opacity,
                         depth=depth)
        g = torch.Generator().manual_seed(seed + 100 + k)
        means = s["means"].clone()
        if scatter:
            means[: n // 5] += 30.0 * torch.randn(n // 5, 3, generator=g, dtype=dtype)
        shN = 0.3 * torch.randn(n, (deg + 1) ** 2 - 1, 3, generator=g, dtype=dtype)
        parts.append(Gaussians(means, s["quats"] * 2.5, torch.log(s["scales"]), torch.logit(s["opacities"]),
                               0.5 * torch.randn(n, 1, 3, generator=g, dtype=dtype), shN))
    behind = random_scene(7, width, height, seed=seed + 50, dtype=dtype)
    parts.append(Gaussians(behind["means"] * torch.tensor([1.0, 1.0, -1.0], dtype=dtype), behind["quats"],
                           torch.log(behind["scales"]), torch.logit(behind["opacities"]),
                           torch.zeros(7, 1, 3, dtype=dtype), torch.zeros(7, 3, 3, dtype=dtype)))
    parts.append(Gaussians(*(torch.zeros((0,) + t.shape[1:], dtype=dtype) for t in
                             (parts[0].means, parts[0].quats, parts[0].scales, parts[0].opacities, parts[0].sh0,
                              parts[1].shN))))
    return parts, Camera.from_world_to_cam(s["viewmat"], s["K"], width, height)


def leaves(parts):
    return [Gaussians(*(getattr(p, k).detach().clone().requires_grad_(True) for k in GAUSSIAN_KEYS)) for p in parts]


def reference(rast, parts, camera, sh_degree, settings):
    """The slow obvious composition: torch activations and SH, concatenation, ``rasterize``."""
    g = Gaussians.cat(parts)
    splats = Splats(g.means, g.quats, g.activated_scales, g.activated_opacities, g.colors(camera.center, sh_degree))
    return rast.rasterize(splats, camera, settings)


def projection_loss(out, seed=5):
    """A random projection of every differentiable output (rgb, depth, alpha)."""
    gen = torch.Generator().manual_seed(seed)
    dt = out.rgb.dtype
    h, w = out.rgb.shape[:2]
    return ((out.rgb * torch.randn(h, w, 3, generator=gen, dtype=dt)).sum()
            + (out.depth * 0.1 * torch.randn(h, w, 1, generator=gen, dtype=dt)).sum()
            + (out.alpha * torch.randn(h, w, 1, generator=gen, dtype=dt)).sum())


def compare(dtype, sh_degree, seed, rtol_grad):
    parts, camera = raw_parts(seed, dtype)
    bg = torch.tensor([0.2, 0.4, 0.6], dtype=dtype)
    settings = RasterSettings(background=bg)
    rast = CpuRasterizer(num_threads=2)
    fused_in, ref_in = leaves(parts), leaves(parts)
    fused, kept = rast.rasterize_gaussians_train(fused_in, camera, sh_degree, settings)
    ref = reference(rast, ref_in, camera, sh_degree, settings)
    N = sum(len(p) for p in parts)
    assert kept < N - 7  # the culling rejected the part behind the camera and scattered ones
    assert float(ref.alpha.detach().max()) > 0.5 and int((ref.radii > 0).sum()) > 100  # a real picture
    projection_loss(fused).backward()
    projection_loss(ref).backward()
    tol_px = 1e-12 if dtype == torch.float64 else 2e-6
    for key in ("rgb", "alpha", "depth"):
        a, b = getattr(fused, key).detach(), getattr(ref, key).detach()
        assert a.shape == b.shape, key
        scale = float(b.abs().max()) if key == "depth" else 1.0
        assert float((a - b).abs().max()) <= tol_px * scale, key
    return fused, ref, fused_in, ref_in


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_fused_matches_reference_float64(sh_degree):
    """Pixels, depth, alpha, radii, AbsGrad and the gradient of every raw tensor of every
    part agree with the torch composition to 1e-9 (relative to the largest entry)."""
    fused, ref, fused_in, ref_in = compare(torch.float64, sh_degree, seed=sh_degree, rtol_grad=1e-9)
    assert torch.equal(fused.radii, ref.radii)
    torch.testing.assert_close(fused.absgrad2d, ref.absgrad2d, rtol=0, atol=1e-9 * float(ref.absgrad2d.abs().max()))
    assert float(fused.absgrad2d.abs().sum()) > 0
    for pi, (a, b) in enumerate(zip(fused_in, ref_in)):
        for k in GAUSSIAN_KEYS:
            ga = getattr(a, k).grad
            gb = getattr(b, k).grad
            if ga is None or gb is None:
                # no gradient at all (shN of parts drawn with band 0 only), as Gaussians.colors
                # leaves it: the optimiser must not see zeros
                assert k == "shN" and (sh_degree == 0 or getattr(a, k).shape[1] == 0), (pi, k)
                assert ga is None and (gb is None or gb.numel() == 0), (pi, k)
                continue
            assert ga.shape == getattr(a, k).shape, (pi, k)
            if ga.numel() == 0:
                continue
            scale = max(1.0, float(gb.abs().max()))
            assert float((ga - gb).abs().max()) <= 1e-9 * scale, (pi, k, float((ga - gb).abs().max()))
    # bands above the requested degree get no gradient; the part behind the camera none at all
    for p in fused_in:
        if len(p) and sh_degree > 0 and p.shN.shape[1] > (sh_degree + 1) ** 2 - 1:
            assert float(p.shN.grad[:, (sh_degree + 1) ** 2 - 1:].abs().max()) == 0.0
    assert all(float(getattr(fused_in[-2], k).grad.abs().max()) == 0.0 for k in GAUSSIAN_KEYS
               if getattr(fused_in[-2], k).grad is not None)
    assert int((fused.radii[-7:] > 0).sum()) == 0


@pytest.mark.parametrize("sh_degree", [0, 3])
def test_fused_matches_reference_float32(sh_degree):
    """The float32 (AVX2) kernel: pixels to 2e-6, gradients and AbsGrad to 1e-4 of the
    largest entry (sums in another order), the same Gaussians drawn."""
    fused, ref, fused_in, ref_in = compare(torch.float32, sh_degree, seed=10 + sh_degree, rtol_grad=1e-4)
    assert torch.equal(fused.radii > 0, ref.radii > 0)
    assert int((fused.radii - ref.radii).abs().max()) <= 1
    torch.testing.assert_close(fused.absgrad2d, ref.absgrad2d, rtol=0, atol=1e-4 * float(ref.absgrad2d.abs().max()))
    for pi, (a, b) in enumerate(zip(fused_in, ref_in)):
        for k in GAUSSIAN_KEYS:
            ga, gb = getattr(a, k).grad, getattr(b, k).grad
            if ga is None or gb is None:  # see the float64 test
                assert k == "shN" and ga is None and (gb is None or gb.numel() == 0), (pi, k)
            elif ga.numel():
                assert float((ga - gb).abs().max()) <= 1e-4 * max(1.0, float(gb.abs().max())), (pi, k)


def test_culling_changes_nothing_and_absgrad_accumulates():
    """cull=False renders the same pixels (the rejected Gaussians could not be drawn) and
    gives the same gradients; AbsGrad adds up over backward passes like ``rasterize``'s."""
    parts, camera = raw_parts(21, torch.float64, degrees=(2, 0))
    rast = CpuRasterizer(num_threads=1)
    a_in, b_in = leaves(parts), leaves(parts)
    a, kept_a = rast.rasterize_gaussians_train(a_in, camera, 2, RasterSettings(), cull=True)
    b, kept_b = rast.rasterize_gaussians_train(b_in, camera, 2, RasterSettings(), cull=False)
    assert kept_a < kept_b == sum(len(p) for p in parts)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.radii, b.radii)
    projection_loss(a).backward()
    projection_loss(b).backward()
    for pa, pb in zip(a_in, b_in):
        for k in GAUSSIAN_KEYS:
            ga, gb = getattr(pa, k).grad, getattr(pb, k).grad
            assert (ga is None and gb is None) or torch.equal(ga, gb), k
    first = a.absgrad2d.clone()
    a2, _ = rast.rasterize_gaussians_train(a_in, camera, 2, RasterSettings(), cull=True)
    a2.absgrad2d.copy_(first)  # the trainer accumulates into one buffer per render; here: twice
    projection_loss(a2).backward()
    torch.testing.assert_close(a2.absgrad2d, 2 * first)


def test_fused_gradcheck_float64():
    """Central differences on a tiny well-conditioned scene (opacities 0.2-0.7: no clamp,
    no skip/stop decision flips under 1e-6). Means use SH degree 0: the colour's view
    direction is detached by design (as ``Gaussians.colors``), which finite differences
    would see; the other tensors are checked with all bands."""
    parts, camera = raw_parts(3, torch.float64, degrees=(3, 1), n=5, width=24, height=20, opacity=(0.2, 0.7),
                              depth=(2.0, 4.0), scatter=False)
    parts = parts[:2]
    rast = CpuRasterizer(num_threads=1)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)
    out0, _ = rast.rasterize_gaussians_train(parts, camera, 3, RasterSettings(background=bg))
    assert int((out0.radii > 0).sum()) >= 7 and float(out0.alpha.detach().max()) > 0.3

    for key in GAUSSIAN_KEYS:
        degree = 0 if key == "means" else 3

        def f(x0, x1, key=key, degree=degree):
            ps = [Gaussians(**{k: (x if k == key else getattr(p, k)) for k in GAUSSIAN_KEYS})
                  for p, x in zip(parts, (x0, x1))]
            out, _ = rast.rasterize_gaussians_train(ps, camera, degree, RasterSettings(background=bg))
            return projection_loss(out, seed=7)

        xs = tuple(getattr(p, key).detach().clone().requires_grad_(True) for p in parts)
        assert torch.autograd.gradcheck(f, xs, eps=1e-6, atol=1e-6, rtol=1e-4), key


def test_fused_refuses_non_finite_and_bad_shapes():
    parts, camera = raw_parts(5, torch.float32, degrees=(1, 0))
    rast = CpuRasterizer()
    bad = leaves(parts)
    with torch.no_grad():
        bad[1].opacities[3] = math.nan
    with pytest.raises(RasterInputError, match=f"row {len(parts[0]) + 3}"):
        rast.rasterize_gaussians_train(bad, camera, 1)
    with pytest.raises(RasterInputError, match="no parts"):
        rast.rasterize_gaussians_train([], camera, 1)
    wrong = Gaussians(parts[0].means[:, :2].contiguous(), *(getattr(parts[0], k) for k in GAUSSIAN_KEYS[1:]))
    with pytest.raises(RasterInputError, match="expected \\(N, 3\\)"):
        rast.rasterize_gaussians_train([wrong], camera, 1)


def assert_same_render(a, b, a_in, b_in, dtype) -> float:
    """Renders ``a`` and ``b`` agree in pixels, radii and AbsGrad, and the raw tensors of
    their inputs ``a_in`` / ``b_in`` in their gradients (dense or row-sparse), to the dtype's
    rounding; returns that tolerance."""
    tol = 1e-10 if dtype == torch.float64 else 1e-4
    for key in ("rgb", "alpha"):
        assert float((getattr(a, key) - getattr(b, key)).detach().abs().max()) <= tol, key
    assert torch.equal(a.radii, b.radii)
    torch.testing.assert_close(a.absgrad2d, b.absgrad2d, rtol=0, atol=tol * float(b.absgrad2d.abs().max()))
    for pa, pb in zip(a_in, b_in):
        for k in GAUSSIAN_KEYS:
            ga, gb = getattr(pa, k).grad, getattr(pb, k).grad
            if gb is None or gb.numel() == 0:
                continue
            ga, gb = ga.to_dense(), gb.to_dense()
            assert float((ga - gb).abs().max()) <= tol * max(1.0, float(gb.abs().max())), k
    return tol


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_moved_scene_matches_moved_copies(dtype):
    """``moved=(R, t)`` (the view matrix composed with the move, view directions moved, the
    gradients of R and t summed from the rows' own) gives the pixels and gradients of drawing
    copies moved by :meth:`Gaussians.transform`, to every raw tensor and, through R and t, to
    a camera-pose correction (axis-angle + translation)."""
    from omnire.geometry import axis_angle_to_rotmat

    parts, camera = raw_parts(11, dtype)
    settings = RasterSettings(background=torch.tensor([0.2, 0.4, 0.6], dtype=dtype))
    rast = CpuRasterizer(num_threads=2)
    base = torch.tensor([0.04, -0.03, 0.05, 0.2, -0.1, 0.15], dtype=dtype)
    outs = {}
    for fused in (True, False):
        ins = leaves(parts)
        delta = base.clone().requires_grad_(True)
        R, t = axis_angle_to_rotmat(delta[:3]), delta[3:]
        if fused:
            out, _ = rast.rasterize_gaussians_train(ins, camera, 3, settings, moved=(R, t))
        else:
            out, _ = rast.rasterize_gaussians_train([p.transform(R, t) for p in ins], camera, 3, settings)
        projection_loss(out).backward()
        outs[fused] = (out, ins, delta)
    (a, a_in, a_d), (b, b_in, b_d) = outs[True], outs[False]
    assert float(b.alpha.detach().max()) > 0.5 and int((b.radii > 0).sum()) > 100
    tol = assert_same_render(a, b, a_in, b_in, dtype)
    assert float(b_d.grad.abs().min()) > 0  # every component of the correction is seen
    torch.testing.assert_close(a_d.grad, b_d.grad, rtol=tol * 10, atol=tol * float(b_d.grad.abs().max()))


def test_moved_gradcheck_float64():
    """Central differences of the move's gradient (axis-angle and translation of a pose
    correction, through R, t and R's quaternion) on a tiny scene; SH degree 0, since the
    colour's view direction is detached by design and finite differences would see it."""
    from omnire.geometry import axis_angle_to_rotmat

    parts, camera = raw_parts(3, torch.float64, degrees=(3, 1), n=5, width=24, height=20, opacity=(0.2, 0.7),
                              depth=(2.0, 4.0), scatter=False)
    parts = parts[:2]
    rast = CpuRasterizer(num_threads=1)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)

    def f(delta):
        moved = (axis_angle_to_rotmat(delta[:3]), delta[3:])
        out, _ = rast.rasterize_gaussians_train(parts, camera, 0, RasterSettings(background=bg), moved=moved)
        return projection_loss(out, seed=7)

    delta = torch.tensor([0.01, -0.02, 0.015, 0.03, -0.01, 0.02], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(f, (delta,), eps=1e-6, atol=1e-6, rtol=1e-4)


def placed_inputs(parts, seed, dtype, lengths=(40, 0, 60, 50)):
    """Box-local copies of parts 0 and 3 (segments ``lengths``) and pose parameters
    (axis-angle (P,3), translation (P,3)) that put them back where ``parts`` has them."""
    from omnire.geometry import axis_angle_to_rotmat
    from omnire.placement import Placement

    g = torch.Generator().manual_seed(seed)
    P = len(lengths)
    rot = 0.6 * torch.randn(P, 3, generator=g, dtype=dtype)
    trans = torch.randn(P, 3, generator=g, dtype=dtype)
    R = axis_angle_to_rotmat(rot)
    inverse = Placement(list(lengths), R.transpose(1, 2), -(R.transpose(1, 2) @ trans[..., None])[..., 0])
    local = [inverse.apply(p) if k in (0, 3) else p for k, p in enumerate(parts)]
    return local, rot, trans


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
@pytest.mark.parametrize("with_move", [False, True])
def test_placed_parts_match_world_copies(dtype, with_move):
    """``placements`` (box-local rows drawn through per-segment composed view matrices, the
    poses' gradients summed per segment) gives the pixels and gradients of drawing the world
    copies :meth:`Placement.apply` makes, alone and under a camera-pose move; to every raw
    tensor, to the poses, and to the move."""
    from omnire.geometry import axis_angle_to_rotmat
    from omnire.placement import Placement

    parts, camera = raw_parts(5, dtype)
    local, rot0, trans0 = placed_inputs(parts, 9, dtype)
    settings = RasterSettings(background=torch.tensor([0.2, 0.4, 0.6], dtype=dtype))
    rast = CpuRasterizer(num_threads=2)
    base = torch.tensor([0.04, -0.03, 0.05, 0.2, -0.1, 0.15], dtype=dtype)
    outs = {}
    for fused in (True, False):
        ins = leaves(local)
        rot, trans = rot0.clone().requires_grad_(True), trans0.clone().requires_grad_(True)
        delta = base.clone().requires_grad_(True)
        moved = (axis_angle_to_rotmat(delta[:3]), delta[3:]) if with_move else None
        placements = [Placement([40, 0, 60, 50], axis_angle_to_rotmat(rot), trans) if k in (0, 3) else None
                      for k in range(len(ins))]
        if fused:
            out, _ = rast.rasterize_gaussians_train(ins, camera, 3, settings, moved=moved, placements=placements)
        else:
            world = [p if pl is None else pl.apply(p) for p, pl in zip(ins, placements)]
            out, _ = rast.rasterize_gaussians_train(world, camera, 3, settings, moved=moved)
        projection_loss(out).backward()
        outs[fused] = (out, ins, rot, trans, delta)
    (a, a_in, a_rot, a_tr, a_d), (b, b_in, b_rot, b_tr, b_d) = outs[True], outs[False]
    assert float(b.alpha.detach().max()) > 0.5 and int((b.radii[:150] > 0).sum()) > 50
    tol = assert_same_render(a, b, a_in, b_in, dtype)
    for ga, gb in ((a_rot.grad, b_rot.grad), (a_tr.grad, b_tr.grad)) + (((a_d.grad, b_d.grad),) if with_move else ()):
        assert float(gb[[0, 2, 3]].abs().min()) > 0  # the segments with rows see every component
        torch.testing.assert_close(ga, gb, rtol=tol * 10, atol=tol * float(gb.abs().max()))


def test_placed_gradcheck_float64():
    """Central differences of the placement poses' gradient (axis-angle and translation per
    segment, composed with a camera-pose move) on a tiny scene, SH degree 0 (the colour's view
    direction is detached by design)."""
    from omnire.geometry import axis_angle_to_rotmat
    from omnire.placement import Placement

    parts, camera = raw_parts(3, torch.float64, degrees=(3, 1), n=6, width=24, height=20, opacity=(0.2, 0.7),
                              depth=(2.0, 4.0), scatter=False)
    parts = parts[:2]
    lengths = [2, 4]
    rot0 = torch.tensor([[0.02, -0.01, 0.03], [-0.02, 0.01, 0.01]], dtype=torch.float64)
    trans0 = torch.tensor([[0.05, -0.02, 0.01], [0.0, 0.03, -0.04]], dtype=torch.float64)
    local = [Placement(lengths, axis_angle_to_rotmat(rot0).transpose(1, 2),
                       -(axis_angle_to_rotmat(rot0).transpose(1, 2) @ trans0[..., None])[..., 0]).apply(parts[0]),
             parts[1]]
    rast = CpuRasterizer(num_threads=1)
    bg = torch.tensor([0.3, 0.6, 0.9], dtype=torch.float64)

    def f(rot, trans, delta):
        moved = (axis_angle_to_rotmat(delta[:3]), delta[3:])
        placements = [Placement(lengths, axis_angle_to_rotmat(rot), trans), None]
        out, _ = rast.rasterize_gaussians_train(local, camera, 0, RasterSettings(background=bg), moved=moved,
                                                placements=placements)
        return projection_loss(out, seed=7)

    delta = torch.tensor([0.01, -0.02, 0.015, 0.03, -0.01, 0.02], dtype=torch.float64, requires_grad=True)
    rot, trans = rot0.clone().requires_grad_(True), trans0.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (rot, trans, delta), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_placements_are_checked():
    from omnire.placement import Placement

    parts, camera = raw_parts(2, torch.float32, n=20)
    rast = CpuRasterizer(num_threads=1)
    eye = torch.eye(3)[None].repeat(2, 1, 1)
    with pytest.raises(RasterInputError, match="one per part"):
        rast.rasterize_gaussians_train(parts, camera, 1, placements=[None])
    wrong = [Placement([5, 10], eye, torch.zeros(2, 3))] + [None] * (len(parts) - 1)
    with pytest.raises(RasterInputError, match="20 Gaussians, the segments hold 15 rows"):
        rast.rasterize_gaussians_train(parts, camera, 1, placements=wrong)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_placement_starts_draw_picked_rows_in_place(dtype):
    """A placement with ``starts`` draws those rows of a part in place (e.g. a node's
    parameters, no gathered copy): the pixels, radii and AbsGrad of drawing the gathered rows,
    and the same gradients, row-sparse over the picked rows (other rows get none)."""
    from omnire.geometry import axis_angle_to_rotmat
    from omnire.placement import Placement
    from omnire.rowsparse import gather_rows

    parts, camera = raw_parts(7, dtype)
    local, rot0, trans0 = placed_inputs(parts, 3, dtype, lengths=(40, 0, 60, 50))
    source = local[0]  # 150 rows; pick 3 segments of it, with rows left out between them
    starts, lengths = [5, 50, 60, 120], [30, 0, 45, 25]
    rows = torch.cat([torch.arange(s, s + n) for s, n in zip(starts, lengths)])
    settings = RasterSettings(background=torch.tensor([0.2, 0.4, 0.6], dtype=dtype))
    rast = CpuRasterizer(num_threads=2)
    outs = {}
    for in_place in (True, False):
        ins = leaves([source, local[1]])
        rot, trans = rot0.clone().requires_grad_(True), trans0.clone().requires_grad_(True)
        R = axis_angle_to_rotmat(rot)
        if in_place:
            parts_in = ins
            placement = Placement(lengths, R, trans, starts=starts)
            assert torch.equal(placement.rows, rows)
        else:
            parts_in = [Gaussians(*(gather_rows(getattr(ins[0], k), rows) for k in GAUSSIAN_KEYS)), ins[1]]
            placement = Placement(lengths, R, trans)
        moved = (axis_angle_to_rotmat(torch.tensor([0.02, -0.01, 0.03], dtype=dtype)),
                 torch.tensor([0.1, 0.0, -0.1], dtype=dtype))
        out, _ = rast.rasterize_gaussians_train(parts_in, camera, 3, settings, moved=moved,
                                                placements=[placement, None])
        projection_loss(out).backward()
        outs[in_place] = (out, ins, rot, trans)
    (a, a_in, a_rot, a_tr), (b, b_in, b_rot, b_tr) = outs[True], outs[False]
    assert len(a.radii) == len(rows) + len(local[1]) and int((b.radii[:len(rows)] > 0).sum()) > 30
    tol = assert_same_render(a, b, a_in, b_in, dtype)
    for pa, pb in zip(a_in, b_in):
        assert all(getattr(pa, k).grad.layout == getattr(pb, k).grad.layout for k in GAUSSIAN_KEYS)
    assert a_in[0].means.grad.is_sparse and torch.equal(a_in[0].means.grad._indices()[0], rows)
    for ga, gb in ((a_rot.grad, b_rot.grad), (a_tr.grad, b_tr.grad)):
        torch.testing.assert_close(ga, gb, rtol=tol * 10, atol=tol * float(gb.abs().max()))
