"""``omnire bench humanpose``: the human pose pipeline against ground truth.

On a synthetic scene (``omnire synth crowd <dir>``: ``ground_truth.npz`` holds every
walker's true global orientation and body pose, ``depth/`` the rendered depth) each source
poses every pedestrian from the data alone (the scene's own ``humanpose/smpl.pkl`` is not
read):

- ``neutral``: the fallback standing pose facing the box heading;
- ``<estimator>``: the image estimator's tracklets (IoU-matched, SLERP-completed rotations);
- ``lidar``: the body fitter on LiDAR points only;
- ``<estimator>-fit``: the body fitter on the estimator's 2D keypoints only;
- ``fusion``: the body fitter on LiDAR and keypoints together (the default pipeline).

Per pedestrian-frame: MPJPE (24 joints, pelvis-aligned, metres) and PA-MPJPE (after a
similarity Procrustes alignment), both on the shipped template so they measure rotations;
*visible* = at least 4 joints unoccluded (rendered depth test) in some camera; *posed* =
the source observed that frame (``valid``; the fallback and SLERP-filled frames are not
posed). Aggregates per source, by pedestrian height in pixels and by LiDAR points on the
body, and on the acceptance subset (>= 50 points or >= 80 px). With ``--crop-policies``
the image estimator also runs under several crop policies, each measured by detection rate
and 2D keypoint error against the projected true joints.

Writes ``results.json`` and ``results.md`` to ``--output`` and prints the table.
"""
from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np

HEIGHT_BINS = (0.0, 40.0, 80.0, np.inf)
POINT_BINS = (0, 10, 50, np.inf)


@dataclasses.dataclass
class HumanPoseBenchArgs:
    """Measure the human pose pipeline's sources against a synthetic scene's true body poses."""

    data: Path = Path("outputs/bench/humanpose/crowd")
    """Synthetic scene (``omnire synth crowd DIR``); generated there with --generate when absent."""
    output: Path = Path("outputs/bench/humanpose")
    """Where results.json and results.md go."""
    generate: bool = False
    """Generate the scene into --data first when it holds none (``omnire synth crowd`` with the flags below)."""
    frames: int = 40
    """Frames of a generated scene."""
    width: int = 960
    """Image width of a generated scene."""
    height: int = 540
    """Image height of a generated scene."""
    seed: int = 0
    """Seed of a generated scene."""
    estimator: str = "auto"
    """Image pose estimator (registered name, auto = the best available, none = no image source)."""
    sources: tuple[str, ...] = ("neutral", "estimator", "lidar", "estimator-fit", "fusion")
    """Sources to measure (estimator = the image estimator's own rotations)."""
    crop_policies: bool = False
    """Also measure the image estimator under several crop policies (detection rate, keypoint error)."""
    frame_stride: int = 1
    """Use every n-th frame for the crop-policy measurement."""
    threads: int = 1
    """torch threads."""


# ---------------------------------------------------------------------------------- truth
@dataclasses.dataclass
class Truth:
    """True poses of a synthetic scene in the scene's world: per pedestrian track id,
    global_orient (F, 3, 3), body_pose (F, 23, 3, 3), joints (F, 24, 3) world positions."""

    global_orient: dict
    body_pose: dict
    joints: dict


def load_truth(root: Path, scene, template) -> Truth:
    """Read ``ground_truth.npz`` and move its poses into the scene's world frame (the rigid
    transform that maps the true box poses onto the scene's boxes)."""
    from omnire.api import SceneDataError
    from omnire_body.lbs import forward_kinematics

    path = Path(root) / "ground_truth.npz"
    if not path.is_file():
        raise SceneDataError(f"{path}: not found; `omnire bench humanpose` needs a synthetic scene "
                             "(omnire synth crowd DIR) with its ground truth")
    with np.load(path, allow_pickle=False) as gt:
        ids = [str(x) for x in gt["track_ids"]]
        boxes = gt["box_poses_true"]
        ped_ids = [str(x) for x in gt["pedestrian_ids"]]
        go_true, bp_true, transl = gt["global_orient_true"], gt["body_pose_true"], gt["smpl_transl"]
    by_id = {t.track_id: t for t in scene.tracks}
    # scene world <- generator world, from any present box of a pedestrian
    W = None
    for k, tid in enumerate(ids):
        t = by_id.get(tid)
        if t is not None and t.present.any():
            f = int(np.flatnonzero(t.present)[0])
            W = t.poses[f] @ np.linalg.inv(boxes[k, f])
            break
    if W is None:
        raise SceneDataError(f"{path}: none of its tracks is in the scene")
    out = Truth({}, {}, {})
    J0 = template.joints[0]
    for k, tid in enumerate(ped_ids):
        go = W[:3, :3] @ go_true[k]  # (F, 3, 3)
        out.global_orient[tid] = go
        out.body_pose[tid] = bp_true[k]
        posed, _ = forward_kinematics(template.joints, template.parents, go_true[k], bp_true[k])
        world_gen = posed + transl[k][:, None]  # SMPL: about J0 then translation
        _ = J0
        out.joints[tid] = world_gen @ W[:3, :3].T + W[:3, 3]
    return out


def joint_errors(template, go_est: np.ndarray, bp_est: np.ndarray, go_gt: np.ndarray, bp_gt: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Per-frame MPJPE and PA-MPJPE (F,) in metres over the 24 joints, pelvis-aligned.

    Args: global orientations (F, 3, 3) and body poses (F, 23, 3, 3), estimated and true.
    """
    from omnire_body.lbs import forward_kinematics

    Je, _ = forward_kinematics(template.joints, template.parents, go_est, bp_est)
    Jg, _ = forward_kinematics(template.joints, template.parents, go_gt, bp_gt)
    Je = Je - Je[:, :1]
    Jg = Jg - Jg[:, :1]
    mpjpe = np.linalg.norm(Je - Jg, axis=-1).mean(1)
    return mpjpe, np.array([np.linalg.norm(procrustes(a, b) - b, axis=-1).mean() for a, b in zip(Je, Jg)])


def procrustes(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``a`` (N, 3) after the similarity transform that best maps it onto ``b`` (N, 3)."""
    ma, mb = a.mean(0), b.mean(0)
    A, B = a - ma, b - mb
    U, S, Vt = np.linalg.svd(A.T @ B)
    d = np.sign(np.linalg.det(U @ Vt))
    D = np.diag([1.0, 1.0, d])
    R = (U @ D @ Vt).T
    s = (S * np.diag(D)).sum() / max((A ** 2).sum(), 1e-12)
    return s * A @ R.T + mb


def visibility(root: Path, scene, truth: Truth, min_joints: int = 4, tol: float = 0.15) -> dict:
    """Per pedestrian: (F,) visible flags (>= ``min_joints`` true joints in some image and in
    front of the rendered depth) and (F,) largest projected box height (px) over cameras."""
    from omnire_body.humanpose import project_box

    depth_dir = Path(root) / "depth"
    by_id = {t.track_id: t for t in scene.tracks}
    F = scene.num_frames
    vis = {tid: np.zeros(F, bool) for tid in truth.joints}
    hpx = {tid: np.zeros(F) for tid in truth.joints}
    for f in range(F):
        for c, cam in enumerate(scene.cameras):
            depth = None
            dp = depth_dir / f"{f:03d}_{c}.npy"
            if dp.is_file():
                depth = np.load(dp)
            w2c = np.linalg.inv(cam.cam_to_world[f])
            for tid, J in truth.joints.items():
                t = by_id.get(tid)
                if t is None or not t.present[f]:
                    continue
                box = project_box(t, scene, c, f)
                if box is None:
                    continue
                hpx[tid][f] = max(hpx[tid][f], box[3] - box[1])
                p = J[f] @ w2c[:3, :3].T + w2c[:3, 3]
                z = p[:, 2]
                uv = p[:, :2] / np.maximum(z[:, None], 1e-6) @ cam.intrinsics[:2, :2].T + cam.intrinsics[:2, 2]
                inside = (z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
                if depth is not None and inside.any():
                    sy, sx = depth.shape[0] / cam.height, depth.shape[1] / cam.width
                    r = np.clip((uv[inside, 1] * sy).astype(int), 0, depth.shape[0] - 1)
                    q = np.clip((uv[inside, 0] * sx).astype(int), 0, depth.shape[1] - 1)
                    ok = z[inside] <= depth[r, q] + tol
                    n = int(ok.sum())
                else:
                    n = int(inside.sum())
                if n >= min_joints:
                    vis[tid][f] = True
    return {"visible": vis, "height_px": hpx}


# ---------------------------------------------------------------------------------- runs
def _fresh(scene):
    """A shallow copy of ``scene`` with no human poses."""
    return dataclasses.replace(scene, human_poses={})


class _Replay:
    """An estimator that returns the tracklets another one produced (the image model runs
    once for every source that uses it)."""

    def __init__(self, inner):
        self.inner = inner
        self.name = getattr(inner, "name", "estimator")
        self.cache: dict = {}
        self.seconds = 0.0

    def estimate(self, scene, camera, rois):
        key = (camera, tuple(sorted((f, str(k)) for f, items in rois.items() for k, _ in items)))
        if key not in self.cache:
            t0 = time.perf_counter()
            self.cache[key] = self.inner.estimate(scene, camera, rois)
            self.seconds += time.perf_counter() - t0
        return self.cache[key]


def run_source(scene, source: str, estimator, template) -> tuple[dict, float]:
    """Pose every pedestrian of ``scene`` with one source; returns ({track id: sequence}, seconds)."""
    from omnire_body.humanpose import neutral_sequence, prepare_human_poses

    s = _fresh(scene)
    t0 = time.perf_counter()
    if source == "neutral":
        for t in s.tracks:
            if t.category == "human" and t.present.any():
                s.human_poses[t.track_id] = neutral_sequence(t, template.joints)
    elif source == "estimator":
        prepare_human_poses(s, estimator=estimator, fit=False, fallback="none", template=template)
    elif source == "lidar":
        prepare_human_poses(s, estimator=None, fit=True, fallback="none", template=template)
    elif source == "estimator-fit":
        s = dataclasses.replace(s, lidar=None)
        prepare_human_poses(s, estimator=estimator, fit=True, fallback="none", template=template)
    elif source == "fusion":
        prepare_human_poses(s, estimator=estimator, fit=True, fallback="none", template=template)
    else:
        raise ValueError(f"unknown source {source!r}")
    return s.human_poses, time.perf_counter() - t0


def evaluate(scene, truth: Truth, vis: dict, poses: dict, template, lidar_counts: dict) -> dict:
    """Per-frame records of one source -> aggregate metrics."""
    rows = []
    for tid in truth.joints:
        t = next((x for x in scene.tracks if x.track_id == tid), None)
        if t is None:
            continue
        present = t.present
        seq = poses.get(tid)
        F = len(present)
        if seq is None:
            err = np.full(F, np.nan)
            pa = np.full(F, np.nan)
            posed = np.zeros(F, bool)
        else:
            err, pa = joint_errors(template, seq.global_orient, seq.body_pose, truth.global_orient[tid],
                                   truth.body_pose[tid])
            posed = seq.valid & (seq.source != "neutral") if seq.source != "neutral" else np.zeros(F, bool)
        for f in np.flatnonzero(present & vis["visible"][tid]):
            rows.append((tid, int(f), float(err[f]), float(pa[f]), bool(posed[f]), float(vis["height_px"][tid][f]),
                         int(lidar_counts[tid][f])))
    return aggregate(rows)


def aggregate(rows: list) -> dict:
    """rows of (track, frame, mpjpe, pa_mpjpe, posed, height px, lidar points) -> metrics."""
    if not rows:
        return {"frames": 0}
    err = np.array([r[2] for r in rows])
    pa = np.array([r[3] for r in rows])
    posed = np.array([r[4] for r in rows])
    h = np.array([r[5] for r in rows])
    n = np.array([r[6] for r in rows])

    def block(sel: np.ndarray) -> dict:
        if not sel.any():
            return {"frames": 0}
        e, p = err[sel], pa[sel]
        ok = np.isfinite(e)
        return {"frames": int(sel.sum()), "posed_fraction": float(posed[sel].mean()),
                "mpjpe_cm": float(100 * e[ok].mean()) if ok.any() else None,
                "pa_mpjpe_cm": float(100 * p[ok].mean()) if ok.any() else None,
                "mpjpe_posed_cm": float(100 * e[ok & posed[sel]].mean()) if (ok & posed[sel]).any() else None}

    out = {"all": block(np.ones(len(rows), bool)), "acceptance_subset": block((n >= 50) | (h >= 80)),
           "by_height_px": {}, "by_lidar_points": {}}
    for lo, hi in zip(HEIGHT_BINS[:-1], HEIGHT_BINS[1:]):
        out["by_height_px"][f"{lo:.0f}-{hi:.0f}"] = block((h >= lo) & (h < hi))
    for lo, hi in zip(POINT_BINS[:-1], POINT_BINS[1:]):
        out["by_lidar_points"][f"{lo:.0f}-{hi:.0f}"] = block((n >= lo) & (n < hi))
    return out


# ---------------------------------------------------------------------------------- crop policies
CROP_POLICIES = {  # one region size each (``retry_roi_scales`` off), then the estimator's default
    "detector, margin 0.3, upscale 256": {"mode": "detector", "margin": 0.3, "upscale_to": 256, "mask_occluders": False},
    "roi 1.1 box heights": {"mode": "roi", "roi_scale": 1.1, "upscale_to": 256, "mask_occluders": False},
    "roi 1.25": {"mode": "roi", "roi_scale": 1.25, "upscale_to": 256, "mask_occluders": False},
    "roi 1.5": {"mode": "roi", "roi_scale": 1.5, "upscale_to": 256, "mask_occluders": False},
    "roi 1.25, no bicubic upscale": {"mode": "roi", "roi_scale": 1.25, "upscale_to": 0, "mask_occluders": False},
    "roi 1.25, mask occluder boxes": {"mode": "roi", "roi_scale": 1.25, "upscale_to": 256, "mask_occluders": True,
                                      "mask_shape": "box"},
    "roi 1.25, mask occluder bodies": {"mode": "roi", "roi_scale": 1.25, "upscale_to": 256, "mask_occluders": True,
                                       "mask_shape": "body"},
}
CROP_POLICIES = {name: {**kw, "retry_roi_scales": ()} for name, kw in CROP_POLICIES.items()}
CROP_POLICIES["default: roi 1.25, then 1.5 and 1.1 on a miss, mask occluder bodies"] = {}


def crop_policy_metrics(scene, truth: Truth, vis: dict, spec, frame_stride: int, min_box_height: float) -> dict:
    """Detection rate and 2D keypoint error (median, in box heights, over keypoints with
    confidence >= 0.5) of the estimator under each crop policy, by pedestrian height."""
    from omnire_body.humanpose import estimator_tracklets

    humans = [t for t in scene.tracks if t.category == "human" and t.track_id in truth.joints]
    frames = np.arange(0, scene.num_frames, max(1, frame_stride))
    keep = np.zeros(scene.num_frames, bool)
    keep[frames] = True
    sub = []
    for t in humans:
        t2 = dataclasses.replace(t, present=t.present & keep)
        sub.append(t2)
    out = {}
    for name, kw in CROP_POLICIES.items():
        est = spec.factory(**kw)
        t0 = time.perf_counter()
        tracklets = estimator_tracklets(scene, est, sub, min_box_height)
        secs = time.perf_counter() - t0
        tried, found, errs = _policy_stats(scene, truth, vis, sub, tracklets, min_box_height)
        res = {"seconds": round(secs, 1)}
        for lo, hi in zip(HEIGHT_BINS[:-1], HEIGHT_BINS[1:]):
            sel = (tried[:, 0] >= lo) & (tried[:, 0] < hi)
            e = errs[(errs[:, 0] >= lo) & (errs[:, 0] < hi), 1] if len(errs) else np.zeros(0)
            res[f"{lo:.0f}-{hi:.0f}"] = {"crops": int(sel.sum()),
                                         "detected": float(found[sel].mean()) if sel.any() else None,
                                         "kp_error_median": float(np.median(e)) if len(e) else None}
        out[name] = res
    return out


def _policy_stats(scene, truth, vis, tracks, tracklets, min_box_height):
    """(crops tried (M, 1) height px, found (M,) bool, keypoint errors (K, 2): height, error)."""
    from omnire_body.humanpose import project_box

    det = {}
    for tl in tracklets:
        for i, f in enumerate(tl.frames):
            det[(tl.camera, str(tl.key), int(f))] = (tl, i)
    tried, found, errs = [], [], []
    for t in tracks:
        J = truth.joints[t.track_id]
        for c, cam in enumerate(scene.cameras):
            for f in t.frames():
                f = int(f)
                box = project_box(t, scene, c, f)
                if box is None or box[3] - box[1] < min_box_height or not vis["visible"][t.track_id][f]:
                    continue
                h = box[3] - box[1]
                tried.append([h])
                hit = det.get((c, str(t.track_id), f))
                found.append(hit is not None)
                if hit is None or hit[0].keypoints is None:
                    continue
                kp = hit[0].keypoints[hit[1]]
                w2c = np.linalg.inv(cam.cam_to_world[f])
                p = J[f] @ w2c[:3, :3].T + w2c[:3, 3]
                uv = p[:, :2] / p[:, 2:] @ cam.intrinsics[:2, :2].T + cam.intrinsics[:2, 2]
                ok = kp[:, 2] >= 0.5
                if ok.any():
                    errs.append([h, float(np.median(np.linalg.norm(kp[ok, :2] - uv[ok], axis=1)) / h)])
    return np.array(tried).reshape(-1, 1), np.array(found, bool), np.array(errs).reshape(-1, 2)


# ---------------------------------------------------------------------------------- report
def markdown(results: dict) -> str:
    lines = [f"Scene: `{results['scene']}` ({results['pedestrians']} pedestrians, {results['frames']} frames, "
             f"{results['visible_pedestrian_frames']} visible pedestrian-frames); estimator: {results['estimator']}.", "",
             "| Source | posed (visible frames) | MPJPE cm | PA-MPJPE cm | acceptance subset: frames | posed | MPJPE cm "
             "| PA-MPJPE cm | seconds |", "|" + "---|" * 9]

    def f(v, d=1):
        return "-" if v is None else (f"{100 * v:.0f}%" if d == "%" else f"{v:.{d}f}")

    for name, r in results["sources"].items():
        a, s = r["metrics"]["all"], r["metrics"]["acceptance_subset"]
        lines.append(f"| {name} | {f(a.get('posed_fraction'), '%')} | {f(a.get('mpjpe_cm'))} | {f(a.get('pa_mpjpe_cm'))} "
                     f"| {s.get('frames', 0)} | {f(s.get('posed_fraction'), '%')} | {f(s.get('mpjpe_cm'))} "
                     f"| {f(s.get('pa_mpjpe_cm'))} | {r['seconds']:.0f} |")
    for key, title in (("by_height_px", "pedestrian height (px)"), ("by_lidar_points", "LiDAR points on the body")):
        bins = list(next(iter(results["sources"].values()))["metrics"][key].keys())
        lines += ["", f"MPJPE cm (posed fraction) by {title}:", "",
                  "| Source | " + " | ".join(bins) + " |", "|" + "---|" * (len(bins) + 1)]
        for name, r in results["sources"].items():
            cells = []
            for b in bins:
                m = r["metrics"][key][b]
                cells.append("-" if not m.get("frames") else f"{f(m.get('mpjpe_cm'))} ({f(m.get('posed_fraction'), '%')}, "
                             f"n={m['frames']})")
            lines.append(f"| {name} | " + " | ".join(cells) + " |")
    if results.get("crop_policies"):
        bins = [k for k in next(iter(results["crop_policies"].values())) if k != "seconds"]
        lines += ["", "Image estimator crop policies: detection rate / median 2D keypoint error (box heights) "
                  "by pedestrian height (px):", "", "| Policy | " + " | ".join(bins) + " | seconds |",
                  "|" + "---|" * (len(bins) + 2)]
        for name, r in results["crop_policies"].items():
            cells = [("-" if not r[b]["crops"] else f"{f(r[b]['detected'], '%')} / {f(r[b]['kp_error_median'], 3)} "
                      f"(n={r[b]['crops']})") for b in bins]
            lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['seconds']} |")
    return "\n".join(lines) + "\n"


def run(args: HumanPoseBenchArgs, plugins) -> dict:
    import torch

    from omnire.api import UserError
    from omnire_body.humanpose import select_estimator, track_data
    from omnire_body.template import load_template

    torch.set_num_threads(max(1, args.threads))
    root = Path(args.data)
    if (root / "ground_truth.npz").is_file():
        cfg = plugins.dataparsers.get("processed").config_factory()
    elif not args.generate:
        raise UserError(f"{root}: no synthetic scene (ground_truth.npz); pass --generate or run "
                        f"`omnire synth crowd {root}`")
    else:  # the synthetic dataparser generates the scene, then reads it as the processed reader does
        if "synthetic" not in plugins.dataparsers:
            raise UserError("--generate needs the synthetic dataparser (pip install -e dataparsers/synthetic)")
        cfg = plugins.dataparsers.get("synthetic").config_factory()
        cfg = dataclasses.replace(cfg, preset="crowd", regenerate=True, generator=dataclasses.replace(
            cfg.generator, seed=args.seed, frames=args.frames, width=args.width, height=args.height))
    cfg = dataclasses.replace(cfg, data=root, scale=1.0, load_human_poses=False)
    scene = cfg.setup().parse()
    template = load_template()
    truth = load_truth(root, scene, template)
    vis = visibility(root, scene, truth)
    estimator = None if args.estimator == "none" else select_estimator(plugins.pose_estimators, args.estimator)
    replay = _Replay(estimator) if estimator is not None else None
    est_name = getattr(estimator, "name", "none")
    counts = {}
    for t in scene.tracks:
        if t.track_id in truth.joints:
            counts[t.track_id] = track_data(scene, t, []).lidar_counts()
    results = {"scene": str(root), "frames": scene.num_frames, "pedestrians": len(truth.joints),
               "visible_pedestrian_frames": int(sum(v.sum() for v in vis["visible"].values())),
               "estimator": est_name, "sources": {}}
    for source in args.sources:
        if source in ("estimator", "estimator-fit") and replay is None:
            continue
        poses, secs = run_source(scene, source, replay, template)
        label = {"estimator": est_name, "estimator-fit": f"{est_name}-fit"}.get(source, source)
        results["sources"][label] = {"seconds": secs, "metrics": evaluate(scene, truth, vis, poses, template, counts)}
    if replay is not None:
        results["estimator_seconds"] = replay.seconds
    if args.crop_policies and estimator is not None:
        spec_e = plugins.pose_estimators.get(est_name)
        results["crop_policies"] = crop_policy_metrics(scene, truth, vis, spec_e, args.frame_stride, 16.0)
    return results


def main(argv: list[str], plugins) -> int:
    import tyro

    from omnire.api import atomic_write_text

    args = tyro.cli(HumanPoseBenchArgs, args=argv, prog="omnire bench humanpose")
    results = run(args, plugins)
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "results.json", json.dumps(results, indent=1))
    table = markdown(results)
    atomic_write_text(out / "results.md", table)
    print(table)
    return 0
