"""The native CPU rasterizer: :class:`CpuRasterizer` and its autograd function.

The C++ kernel returns the un-normalised accumulations per pixel (colour sum ``acc`` (H,W,D),
depth numerator ``dn`` (H,W), alpha ``a`` (H,W)); background compositing and the expected-
depth division are done here in torch so autograd handles them (they are O(H*W*D)).
float64 inputs run the double-precision kernel (used by gradient checks); anything else is
computed in float32 and the gradients are cast back by autograd.
"""
from __future__ import annotations

from typing import Optional

import torch

from omnire.api import (
    GAUSSIAN_KEYS,
    Camera,
    Gaussians,
    LidarRays,
    LidarRenderOutput,
    LidarSettings,
    Placement,
    RasterInputError,
    RasterSettings,
    RenderOutput,
    Splats,
    check_raster_inputs,
    quat_multiply,
    rotmat_to_quat,
    row_sparse,
)

from ._build import extension as _ext
from .lidar import rasterize_lidar as native_rasterize_lidar
from .ssim import ssim_map as native_ssim_map


class _RasterizeFn(torch.autograd.Function):
    """(means, quats, scales, opacities, colors) -> (acc, dn, alpha, radii, means2d).

    Shapes: means (N,3), quats (N,4), scales (N,3), opacities (N,), colors (N,D) ->
    acc (H,W,D), dn (H,W), alpha (H,W), radii (N,) int32, means2d (N,2).
    ``absgrad`` (N,2) is a plain buffer: the backward adds sum_pixels |dL/dmeans2d| into it.
    No gradients flow to viewmat or K.
    """

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, colors, viewmat, K, absgrad, settings):
        width, height, near, far, eps2d, nthreads = settings
        acc, dn, alpha, radii, means2d, rec, offsets, ids = _ext().forward(
            means, quats, scales, opacities, colors, viewmat, K, width, height, near, far, eps2d, nthreads
        )
        ctx.settings = settings
        ctx.absgrad = absgrad
        ctx.save_for_backward(means, quats, scales, colors, viewmat, K, rec, offsets, ids, radii, acc, dn, alpha)
        ctx.mark_non_differentiable(radii)
        return acc, dn, alpha, radii, means2d

    @staticmethod
    def backward(ctx, g_acc, g_dn, g_alpha, _g_radii, g_means2d):
        means, quats, scales, colors, viewmat, K, rec, offsets, ids, radii, acc, dn, alpha = ctx.saved_tensors
        width, height, near, far, eps2d, nthreads = ctx.settings

        def grad_or_zeros(g, like):
            return torch.zeros_like(like) if g is None else g.contiguous().to(like.dtype)

        g_m2d = (torch.zeros(means.shape[0], 2, dtype=means.dtype) if g_means2d is None
                 else g_means2d.contiguous().to(means.dtype))
        g_means, g_quats, g_scales, g_opac, g_colors, absgrad = _ext().backward(
            means, quats, scales, colors, viewmat, K, width, height, near, far, eps2d,
            rec, offsets, ids, radii, acc, dn, alpha,
            grad_or_zeros(g_acc, acc), grad_or_zeros(g_dn, dn), grad_or_zeros(g_alpha, alpha), g_m2d,
            nthreads,
        )
        ctx.absgrad.add_(absgrad.to(ctx.absgrad.dtype))
        return g_means, g_quats, g_scales, g_opac, g_colors, None, None, None, None


def row_moves(parts: list[Gaussians], moved: Optional[tuple[torch.Tensor, torch.Tensor]],
              placements: Optional[list[Optional[Placement]]], dtype: torch.dtype
              ) -> tuple[Optional[tuple[list[int], list[bool]]], Optional[torch.Tensor], Optional[torch.Tensor],
                         Optional[torch.Tensor]]:
    """The moves the parts' rows are drawn under, as :class:`_RasterizeGaussiansFn` takes them:
    segments (row counts (S), moved or not (S)) and their moves R (S,3,3), t (S,3), qa (S,4)
    (differentiable in ``moved`` and the placements' poses); all None when nothing moves. A
    placed part's segment p moves by ``moved`` after its pose: R = R_m R_p, t = R_m t_p + t_m,
    qa = q_m q_p; a part in the world has one segment, moved by ``moved`` or not at all."""
    if placements is not None and len(placements) != len(parts):
        raise RasterInputError(f"placements: {len(placements)} for {len(parts)} parts, expected one per part "
                               "(None for a part in the world)")
    if moved is not None:
        R_m, t_m = moved
        if R_m.shape != (3, 3) or t_m.shape != (3,):
            raise RasterInputError(f"moved: rotation {tuple(R_m.shape)} and translation {tuple(t_m.shape)}, "
                                   "expected (3, 3) and (3,)")
        R_m, t_m = R_m.to(dtype), t_m.to(dtype)
        q_m = rotmat_to_quat(R_m)
    if moved is None and (placements is None or all(p is None for p in placements)):
        return None, None, None, None
    identity = (torch.eye(3, dtype=dtype)[None], torch.zeros(1, 3, dtype=dtype),
                torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=dtype))
    rows: list[int] = []
    on: list[bool] = []
    Rs, ts, qs = [], [], []
    for part, placement in zip(parts, placements or [None] * len(parts)):
        if placement is None:
            rows.append(len(part))
            on.append(moved is not None)
            if moved is None:
                R, t, q = identity
            else:
                R, t, q = R_m[None], t_m[None], q_m[None]
        else:
            try:
                placement.check_source(len(part))
            except ValueError as exc:
                raise RasterInputError(f"placements: {exc}") from None
            rows.extend(placement.lengths)
            on.extend([True] * len(placement.lengths))
            R, t = placement.R.to(dtype), placement.t.to(dtype)
            q = rotmat_to_quat(R)
            if moved is not None:
                R, t, q = R_m @ R, t @ R_m.T + t_m, quat_multiply(q_m.expand_as(q), q)
        Rs.append(R)
        ts.append(t)
        qs.append(q)
    return (rows, on), torch.cat(Rs), torch.cat(ts), torch.cat(qs)


def kernel_groups(tensors: tuple[torch.Tensor, ...], picks: list[Optional[tuple]]
                  ) -> tuple[list[list[torch.Tensor]], torch.Tensor, torch.Tensor]:
    """The kernel's groups (6 lists, one tensor per group each), the rows of its tensors each
    group draws ((G, 2): first row, rows) and the block of each group: a part is one group, a
    part with picked rows one group per segment (its tensors, uncopied, with the segment's
    rows), all in the part's block (one gradient tensor per parameter)."""
    groups: list[list[torch.Tensor]] = [[] for _ in range(6)]
    spans: list[tuple[int, int]] = []
    blocks: list[int] = []
    for i, pick in enumerate(picks):
        part = tensors[6 * i: 6 * i + 6]
        segments = [(0, len(part[0]))] if pick is None else list(zip(pick[0], pick[1]))
        for k in range(6):
            groups[k].extend([part[k]] * len(segments))
        spans.extend(segments)
        blocks.extend([i] * len(segments))
    return (groups, torch.tensor(spans, dtype=torch.int64).reshape(-1, 2),
            torch.tensor(blocks, dtype=torch.int64))


STAGES = ("rows", "depth_order", "binning", "compositing")
"""The kernel's stages, in order, as :attr:`RenderOutput.timings` names them (``raster.`` first):
culling, activation, projection and SH colour of the rows; the depth sort and gather of the
drawn ones; tile binning; per-pixel compositing."""


def forward_raw(meta, picks, segments, R, t, qa, tensors) -> tuple[list[torch.Tensor], torch.Tensor, dict]:
    """The kernel's forward of raw Gaussians (see :class:`_RasterizeGaussiansFn` for the
    arguments): its outputs (acc, dn, alpha, radii, means2d, records, colours, drawn rows,
    tile offsets, tile ids, Gaussians not rejected), the moves as the kernel takes them
    (rows (S,), moves (S,16) float64, on (S,)) and the stages' wall seconds by name.
    Refuses non-finite rows."""
    sh_degree, center, viewmat, K, width, height, near, far, eps2d, cull, nthreads = meta
    groups, spans, _ = kernel_groups(tensors, picks)
    # x -> R x + t per segment: the kernel draws each through the view matrix composed with its move
    seg_rows = torch.zeros(0, dtype=torch.int64)
    moves = torch.zeros(0, 16, dtype=torch.float64)
    move_on = torch.zeros(0, dtype=torch.bool)
    if segments is not None:
        seg_rows = torch.tensor(segments[0], dtype=torch.int64)
        move_on = torch.tensor(segments[1], dtype=torch.bool)
        moves = torch.cat([R.detach().reshape(-1, 9), t.detach(), qa.detach()], 1).to(torch.float64).contiguous()
    out = _ext().forward_train(*groups, spans, sh_degree, center, seg_rows, moves, move_on, viewmat, K, width,
                               height, near, far, eps2d, cull, nthreads)
    bad, stages = out[10], out[12]
    if int(bad[0]) >= 0:
        raise RasterInputError(f"Gaussian row {int(bad[0])} (of the {len(tensors) // 6} concatenated parts) has "
                               "non-finite parameters or colour; refusing to render a NaN image")
    timings = {f"raster.{name}": float(v) for name, v in zip(STAGES, stages.tolist())}
    return out[:10] + [out[11]], (seg_rows, moves, move_on), timings


class _RasterizeGaussiansFn(torch.autograd.Function):
    """Training path from raw Gaussians in G groups (node outputs, not concatenated).

    Inputs: ``meta`` (non-tensor settings, see :meth:`CpuRasterizer.rasterize_gaussians_train`),
    ``absgrad`` (N, 2) buffer the backward adds AbsGrad into, ``picks`` (per part None, or the
    rows it draws: (starts (P), lengths (P), rows (M,) long) of segments of its rows, drawn in
    place, whose gradients are returned row-sparse), ``segments`` (row counts (S) of
    consecutive segments of the drawn rows, and whether each is moved; None: nothing moved)
    with the segments' moves x -> R x + t (rotations R (S,3,3), translations t (S,3), R's
    quaternions qa (S,4); None without segments), ``timings`` (a dict the stages' wall
    seconds are put in), then 6 tensors per part: means (n,3), quats (n,4), log-scales (n,3),
    opacity logits (n,), sh0 (n,1,3), shN (n,K,3).
    Outputs: acc (H,W,3), depth numerator (H,W), alpha (H,W), radii (N,) int32, means2d (N,2),
    Gaussians not rejected (1,) int64 (the last three carry no gradient). Gradients reach every raw tensor of every group.
    """

    @staticmethod
    def forward(ctx, meta, absgrad, picks, segments, R, t, qa, timings, *tensors):
        (acc, dn, alpha, radii, means2d, rec, col, gidx, offsets, ids, kept), ctx.segments, stages = forward_raw(
            meta, picks, segments, R, t, qa, tensors)
        timings.update(stages)
        if segments is not None:
            ctx.move_rotation = R.detach()
        ctx.meta = meta
        ctx.absgrad = absgrad
        ctx.num_groups = len(tensors) // 6
        ctx.picks = picks
        ctx.save_for_backward(*tensors, rec, col, gidx, offsets, ids, acc, dn, alpha)
        ctx.mark_non_differentiable(radii, means2d, kept)
        return acc, dn, alpha, radii, means2d, kept

    @staticmethod
    def backward(ctx, g_acc, g_dn, g_alpha, _g_radii, _g_means2d, _g_kept):
        sh_degree, center, viewmat, K, width, height, near, far, eps2d, _cull, nthreads = ctx.meta
        saved = ctx.saved_tensors
        G = ctx.num_groups
        tensors = saved[: 6 * G]
        rec, col, gidx, offsets, ids, acc, dn, alpha = saved[6 * G:]
        groups, spans, blocks = kernel_groups(tensors, ctx.picks)

        def grad_or_zeros(g, like):
            return torch.zeros_like(like) if g is None else g.contiguous().to(like.dtype)

        seg_rows, moves, move_on = ctx.segments
        grads = _ext().backward_train(
            *groups, spans, sh_degree, center, seg_rows, moves, move_on, viewmat, K, width, height, near, far,
            eps2d, rec, col, gidx, offsets, ids, acc, dn, alpha,
            grad_or_zeros(g_acc, acc), grad_or_zeros(g_dn, dn), grad_or_zeros(g_alpha, alpha), blocks, nthreads)
        g_R = g_t = g_qa = None
        if bool(move_on.any()):
            # per segment, sums over its rows in the unmoved frame: the moved means' gradient is R g_mean
            sums = grads.pop()
            R = ctx.move_rotation.to(torch.float64)
            g_R = (R @ sums[:, :9].reshape(-1, 3, 3)).to(ctx.move_rotation.dtype)
            g_t = (R @ sums[:, 9:12, None])[..., 0].to(ctx.move_rotation.dtype)
            g_qa = sums[:, 12:].to(ctx.move_rotation.dtype)
        ctx.absgrad.add_(grads[-1].to(ctx.absgrad.dtype))
        grads = grads[:-1]
        for i, pick in enumerate(ctx.picks):
            if pick is None:
                continue
            rows = pick[2]
            for k in range(6):  # the picked rows' gradients, row-sparse as omnire.rowsparse.gather_rows gives them
                if grads[6 * i + k] is not None:
                    grads[6 * i + k] = row_sparse(rows, grads[6 * i + k], tensors[6 * i + k].shape)
        return (None, None, None, None, g_R, g_t, g_qa, None, *grads)


class CpuRasterizer:
    """Native (C++/OpenMP, AVX2) rasterizer implementing :class:`omnire.rasterization.Rasterizer`.

    Args:
        num_threads: OpenMP threads per call (default: ``torch.get_num_threads()`` at call time).
    """

    name = "cpu"

    def __init__(self, num_threads: Optional[int] = None) -> None:
        if num_threads is not None and num_threads < 1:
            raise ValueError(f"num_threads must be >= 1, got {num_threads}")
        self.num_threads = num_threads
        _ext()  # fail at construction, not at the first render

    def rasterize(self, splats: Splats, camera: Camera, settings: RasterSettings = RasterSettings()) -> RenderOutput:
        """See :mod:`omnire.rasterization` for the contract (shapes and semantics)."""
        check_raster_inputs(splats, camera, settings)
        viewmat, K = camera.world_to_cam, camera.K
        for name, t in [("means", splats.means), ("quats", splats.quats), ("scales", splats.scales),
                        ("opacities", splats.opacities), ("colors", splats.colors), ("viewmat", viewmat), ("K", K)]:
            if t.device.type != "cpu":
                raise RasterInputError(f"{name}: on {t.device}; the cpu rasterizer needs CPU tensors")
        dtype = torch.float64 if splats.means.dtype == torch.float64 else torch.float32

        def prep(t: torch.Tensor) -> torch.Tensor:
            return t.to(dtype).contiguous()

        absgrad = torch.zeros(splats.means.shape[0], 2, dtype=dtype)
        nthreads = self.num_threads or torch.get_num_threads()
        raster_settings = (int(camera.width), int(camera.height), float(settings.near), float(settings.far),
                           float(settings.eps2d), int(nthreads))
        acc, dn, alpha, radii, means2d = _RasterizeFn.apply(
            prep(splats.means), prep(splats.quats), prep(splats.scales), prep(splats.opacities), prep(splats.colors),
            viewmat.detach().to(torch.float64).contiguous(), K.detach().to(torch.float64).contiguous(),
            absgrad, raster_settings,
        )
        rgb = acc
        if settings.background is not None:
            rgb = acc + (1.0 - alpha)[..., None] * settings.background.to(dtype)
        depth = dn / alpha.clamp_min(1e-10)
        return RenderOutput(
            rgb=rgb, depth=depth[..., None], alpha=alpha[..., None], radii=radii, means2d=means2d,
            absgrad2d=absgrad,
        )

    def rasterize_gaussians(self, parts: list[Gaussians], camera: Camera, sh_degree: int,
                            settings: RasterSettings = RasterSettings(), cull: bool = True,
                            moved: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
                            placements: Optional[list[Optional[Placement]]] = None
                            ) -> tuple[RenderOutput, int]:
        """Inference-only rendering of raw Gaussians in parts: the forward of
        :meth:`rasterize_gaussians_train` (same arguments, same pixels) with nothing kept for
        a backward pass. Gaussians that cannot reach the image are rejected before their
        covariance is built (``cull``); activation and SH colour (bands up to ``sh_degree``,
        seen from the camera centre) run only for the others. ``RenderOutput.timings`` holds the kernel's stages (:data:`STAGES`). Returns the
        output and the number of Gaussians not rejected. No gradients: call without autograd."""
        if torch.is_grad_enabled() and any(p.means.requires_grad for p in parts):
            raise RuntimeError("rasterize_gaussians is inference-only: call it under torch.no_grad()")
        meta, picks, segments, R, t, qa, tensors = self._raw_inputs(parts, camera, sh_degree, settings, cull, moved,
                                                                    placements)
        (acc, dn, alpha, radii, means2d, *_, kept), _, timings = forward_raw(meta, picks, segments, R, t, qa,
                                                                              tensors)
        return self._output(acc, dn, alpha, radii, means2d, torch.zeros(len(radii), 2), settings, timings), int(kept[0])

    def rasterize_gaussians_train(self, parts: list[Gaussians], camera: Camera, sh_degree: int,
                                  settings: RasterSettings = RasterSettings(), cull: bool = True,
                                  moved: Optional[tuple[torch.Tensor, torch.Tensor]] = None,
                                  placements: Optional[list[Optional[Placement]]] = None
                                  ) -> tuple[RenderOutput, int]:
        """Training rendering of raw Gaussians in parts (node outputs, not concatenated), with
        gradients to every raw tensor of every part: activations (exp of log-scales, sigmoid
        of opacity logits), SH colours from the camera centre (bands up to ``sh_degree``;
        the view direction uses the detached means, as :meth:`Gaussians.colors`) and the
        rejection of Gaussians that cannot reach the image (``cull``) run in the kernel.
        Same pixels as :meth:`rasterize` on the activated, concatenated Gaussians with colours
        from :meth:`Gaussians.colors`, up to float rounding; ``radii`` and ``absgrad2d`` (N,)
        index the parts in order (rejected rows: radius 0, no AbsGrad). float64 parts run in
        double precision (gradient checks). Returns the output and the number of Gaussians
        not rejected.

        ``moved`` = (R (3,3) rotation, t (3,)): draw the parts as if moved by x -> R x + t
        first (rotations composed as ``quat(R) q``, as :meth:`Gaussians.transform`; a camera-
        pose correction, omnire/camerapose.py) without a moved copy of them: the view matrix
        is composed with the move, and R and t get their gradients (through R's quaternion
        too) from the rows' own.

        ``placements`` (one per part, None for a part in the world): a part with a
        :class:`~omnire.placement.Placement` holds box-local rows, drawn placed by their
        segments' poses (after them ``moved``, if given) without a world copy; the poses get
        their gradients the same way. A placement with ``starts`` draws those rows of the part
        (e.g. a node's parameters) in place, and the part's gradients are row-sparse over them.
        Same pixels and gradients as drawing ``placement.apply(part)``, up to float rounding;
        ``radii`` and ``absgrad2d`` then index the drawn rows."""
        meta, picks, segments, R, t, qa, tensors = self._raw_inputs(parts, camera, sh_degree, settings, cull, moved,
                                                                    placements)
        N = sum(len(p) if pick is None else len(pick[2]) for p, pick in zip(parts, picks))
        absgrad = torch.zeros(N, 2, dtype=tensors[0].dtype)
        timings: dict[str, float] = {}
        acc, dn, alpha, radii, means2d, kept = _RasterizeGaussiansFn.apply(meta, absgrad, picks, segments, R, t, qa,
                                                                           timings, *tensors)
        return self._output(acc, dn, alpha, radii, means2d, absgrad, settings, timings), int(kept[0])

    def _raw_inputs(self, parts: list[Gaussians], camera: Camera, sh_degree: int, settings: RasterSettings,
                    cull: bool, moved: Optional[tuple[torch.Tensor, torch.Tensor]],
                    placements: Optional[list[Optional[Placement]]]) -> tuple:
        """The kernel's inputs for raw Gaussian ``parts`` (see :class:`_RasterizeGaussiansFn`):
        (meta, picks, segments, R, t, qa, 6 tensors per part), the parts' tensors checked."""
        if not parts:
            raise RasterInputError("rasterize_gaussians: no parts")
        if camera.device.type != "cpu" or any(p.means.device.type != "cpu" for p in parts):
            raise RasterInputError("the cpu rasterizer needs CPU tensors")
        dtype = torch.float64 if parts[0].means.dtype == torch.float64 else torch.float32
        for p in parts:
            for k in ("means", "quats", "scales", "opacities", "sh0", "shN"):
                t = getattr(p, k)
                if not t.is_floating_point():
                    raise RasterInputError(f"{k}: dtype {t.dtype}, expected a floating type")
            if p.means.ndim != 2 or p.means.shape[1] != 3 or p.scales.shape != p.means.shape:
                raise RasterInputError(f"means / scales: shapes {tuple(p.means.shape)} / {tuple(p.scales.shape)}, "
                                       "expected (N, 3)")
        # shN of a part drawn with band 0 only takes no part (as in Gaussians.colors): detached,
        # so no gradient (not even zeros, which an optimiser would count as a step) reaches it
        tensors = [(t.detach() if k == "shN" and min(int(sh_degree), p.sh_degree) == 0 else t).to(dtype).contiguous()
                   for p in parts for k, t in zip(GAUSSIAN_KEYS, (getattr(p, k) for k in GAUSSIAN_KEYS))]
        picks = [None if pl is None or pl.starts is None else (pl.starts, pl.lengths, pl.rows)
                 for pl in (placements or [None] * len(parts))]
        meta = (int(sh_degree), camera.center.detach().to(torch.float64).contiguous(),
                camera.world_to_cam.detach().to(torch.float64).contiguous(),
                camera.K.detach().to(torch.float64).contiguous(), int(camera.width), int(camera.height),
                float(settings.near), float(settings.far), float(settings.eps2d), bool(cull),
                int(self.num_threads or torch.get_num_threads()))
        segments, R, t, qa = row_moves(parts, moved, placements, dtype)
        return meta, picks, segments, R, t, qa, tensors

    @staticmethod
    def _output(acc, dn, alpha, radii, means2d, absgrad, settings: RasterSettings, timings: dict) -> RenderOutput:
        """The kernel's accumulations as a :class:`RenderOutput`: ``settings.background``
        composited under them, the expected depth divided out."""
        rgb = acc
        if settings.background is not None:
            rgb = acc + (1.0 - alpha)[..., None] * settings.background.to(acc.dtype)
        depth = dn / alpha.clamp_min(1e-10)
        return RenderOutput(rgb=rgb, depth=depth[..., None], alpha=alpha[..., None], radii=radii, means2d=means2d,
                            absgrad2d=absgrad, timings=timings)

    def rasterize_lidar(self, splats: Splats, rays: LidarRays, settings: LidarSettings = LidarSettings()
                        ) -> LidarRenderOutput:
        """The ``lidar`` capability (contract in :mod:`omnire.rasterization`): projection in
        torch, compositing and its backward natively (:mod:`omnire_rasterizer_cpu.lidar`)."""
        return native_rasterize_lidar(splats, rays, settings, self.num_threads or torch.get_num_threads())

    def ssim_map(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """(H, W, C) x2 -> (H, W, 1) SSIM, natively (:mod:`omnire_rasterizer_cpu.ssim`); the
        D-SSIM loss uses it in place of :func:`omnire.losses.ssim_map` (same numbers)."""
        return native_ssim_map(a, b, num_threads=self.num_threads)
