"""Dynamic masks from projected boxes against per-pixel ray casting; sky heuristic."""
import numpy as np
import torch

from omnire.data.images import ImageCache
from omnire.data.scene import View
from omnire.masks import DynamicMasks, SkyMasks, box_polygon, fill_convex

from scene_helpers import LOOK_X


def ray_box_hits(pose, size, c2w, K, W, H):
    """(H,W) bool: does the ray through each pixel centre hit the box (slab test)?"""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    o = c2w[:3, 3]
    # into box coordinates
    d_l = d @ pose[:3, :3]
    o_l = (o - pose[:3, 3]) @ pose[:3, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (-size / 2 - o_l) / d_l
        t2 = (size / 2 - o_l) / d_l
    tmin = np.nanmax(np.minimum(t1, t2), -1)
    tmax = np.nanmin(np.maximum(t1, t2), -1)
    return (tmax >= np.maximum(tmin, 0.1))


def test_box_mask_matches_ray_casting():
    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = LOOK_X
    for yaw, x, y in [(0.3, 8.0, 1.0), (1.2, 5.0, -2.0), (0.0, 1.5, 0.0)]:  # last one crosses the near plane
        pose = np.eye(4)
        pose[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        pose[:3, 3] = [x, y, -0.5]
        size = np.array([4.0, 1.8, 1.5])
        poly = box_polygon(pose, size, np.linalg.inv(c2w), K)
        mask = fill_convex(poly, 80, 60)
        truth = ray_box_hits(pose, size, c2w, K, 80, 60)
        disagree = (mask != truth).mean()
        assert disagree < 0.02, disagree  # only boundary pixels may differ
        assert mask.sum() > 50


def test_dynamic_masks_and_sky(tiny_scene):
    dm = DynamicMasks(tiny_scene, ImageCache(), torch.device("cpu"))
    veh = dm.get(View(0, 0), "vehicle")
    assert veh.shape == (32, 48, 1) and veh.sum() > 0
    assert dm.get(View(0, 0), "human").sum() == 0
    sky = SkyMasks(tiny_scene, ImageCache(), torch.device("cpu")).get(View(0, 1))
    # the tiny scene's wall stops at z = 4 m: the image rows looking above it are sky
    assert sky[0].mean() > 0.9 and sky[-1].sum() == 0


def first_box_by_marching(boxes, c2w, K, W, H, step=0.02, far=25.0):
    """(H,W) index of the first box each pixel's ray is inside of when marched in small steps
    along camera depth (brute force, independent of the slab test); -1 for none."""
    v, u = np.mgrid[0:H, 0:W] + 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ c2w[:3, :3].T
    owner = np.full((H, W), -1)
    depth = np.full((H, W), np.inf)
    zs = np.arange(0.1, far, step)
    for i, (pose, size) in enumerate(boxes):
        pts = c2w[:3, 3] + d[:, :, None, :] * zs[None, None, :, None]  # (H,W,Z,3)
        local = (pts - pose[:3, 3]) @ pose[:3, :3]
        inside = (np.abs(local) <= size / 2).all(-1)
        first = np.where(inside.any(-1), zs[np.argmax(inside, -1)], np.inf)
        nearer = first < depth
        owner[nearer], depth[nearer] = i, first[nearer]
    return owner


def test_nearest_box_owns_the_pixel_pedestrian_behind_a_parked_car(tmp_path):
    from omnire.data.scene import ActorTrack, CameraSequence, SceneData

    K = np.array([[60.0, 0, 40], [0, 60.0, 30], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = LOOK_X  # camera looks along +x, z up
    def pose_at(x, y, z, yaw=0.0):
        p = np.eye(4)
        p[:3, :3] = [[np.cos(yaw), -np.sin(yaw), 0], [np.sin(yaw), np.cos(yaw), 0], [0, 0, 1]]
        p[:3, 3] = [x, y, z]
        return p
    car = (pose_at(6.0, 0.3, -0.8, 0.2), np.array([4.0, 1.8, 1.5]))
    person = (pose_at(10.0, 0.0, -0.2), np.array([0.7, 0.7, 1.8]))  # behind the car, head above it
    tracks = [ActorTrack("ped", "Pedestrian", "human", person[0][None], person[1], np.ones(1, bool)),
              ActorTrack("car", "Car", "vehicle", car[0][None], car[1], np.ones(1, bool))]
    cam = CameraSequence("cam", 80, 60, K, c2w[None], [tmp_path / "x.png"], np.zeros(1))
    scene = SceneData("occl", [cam], np.zeros(1), np.zeros(1, int), np.zeros(1, int), np.zeros(0, int), None, tracks)
    dm = DynamicMasks(scene, ImageCache(), torch.device("cpu"))
    human = dm.get(View(0, 0), "human")[..., 0].numpy() > 0.5
    vehicle = dm.get(View(0, 0), "vehicle")[..., 0].numpy() > 0.5
    truth = first_box_by_marching([person, car], c2w, K, 80, 60)
    assert (human != (truth == 0)).mean() < 0.01 and (vehicle != (truth == 1)).mean() < 0.01
    # The person's box alone would cover pixels the car hides: those go to the car.
    alone = fill_convex(box_polygon(person[0], person[1], np.linalg.inv(c2w), K), 80, 60)
    assert (alone & vehicle).sum() > 20 and not (human & vehicle).any()
    assert human.sum() > 10  # the head above the car stays human


def test_near_upper_limit_against_float64_elevations():
    """Returns within the margin of the LiDAR's upper elevation limit, seen from each frame's
    origin; the limit ignores near returns (the recording vehicle's own, seen from an origin
    that is not exactly the sensor)."""
    from omnire.data.scene import LidarSweeps
    from omnire.lidar import near_upper_limit

    rng = np.random.default_rng(3)
    sweeps, truth = [], []
    origins = np.array([[0.0, 0.0, 0.0], [5.0, 1.0, 0.3]])
    for o in origins:
        el = np.deg2rad(rng.uniform(-25, 12, 4000))  # the sensor's vertical field of view: up to +12 deg
        az, rng_m = rng.uniform(-np.pi, np.pi, 4000), rng.uniform(8, 60, 4000)
        far = o + np.stack([rng_m * np.cos(el) * np.cos(az), rng_m * np.cos(el) * np.sin(az), rng_m * np.sin(el)], 1)
        near = o + np.stack([rng.uniform(-1, 1, 300), rng.uniform(-1, 1, 300), np.full(300, 1.5)], 1)  # ~60-90 deg
        pts = np.concatenate([far, near]).astype(np.float32)
        sweeps.append(pts)
        rel = pts.astype(np.float64) - o
        truth.append(np.degrees(np.arcsin(rel[:, 2] / np.linalg.norm(rel, axis=1))))
    flags = near_upper_limit(LidarSweeps(sweeps, origins), [0, 1], margin_deg=3.0)
    elevation = np.concatenate(truth)
    is_far = np.concatenate([np.arange(len(s)) < 4000 for s in sweeps])
    assert flags[is_far & (elevation > 9.2)].all()  # the limit is ~12 deg (99.5th percentile: >= 11.8)
    assert not flags[is_far & (elevation < 8.7)].any()
    assert flags[~is_far].all()  # near returns above the limit are flagged, but did not set it
    assert near_upper_limit(LidarSweeps(sweeps, np.full((2, 3), np.nan)), [0, 1], 3.0) is None


def _wall_scene(root, width=96, height=64):
    """One camera at the origin looking along +x at a wall (x = 12) whose top is 20 m high for
    y < 0 (far above the LiDAR's +12 deg limit) and 0.5 m for y >= 0 (open sky above it); a
    smooth sky gradient, a checkered wall, LiDAR returns only up to +12 degrees."""
    from omnire.data.scene import CameraSequence, LidarSweeps, SceneData, holdout_split
    from omnire.io.images import write_png

    K = np.array([[60.0, 0, width / 2], [0, 60.0, height / 2], [0, 0, 1]])
    frames = 2
    c2w = np.tile(np.eye(4), (frames, 1, 1))
    c2w[:, :3, :3] = LOOK_X
    v, u = np.mgrid[0:height, 0:width] + 0.5
    d = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ LOOK_X.T
    p = d * (12.0 / d[..., :1])  # where each ray meets the wall's plane
    top = np.where(p[..., 1] < 0, 20.0, 0.5)
    wall = p[..., 2] < top
    sky = 0.6 + 0.2 * v[..., None] / height * np.array([1.0, 1.0, 0.5])
    checker = ((np.floor(2 * p[..., 1]) + np.floor(2 * p[..., 2])) % 2)[..., None]
    img = np.where(wall[..., None], 0.2 + 0.5 * checker * np.array([1.0, 0.5, 0.3]), sky)
    paths = []
    for f in range(frames):
        paths.append(root / f"{f}.png")
        write_png(paths[-1], img)
    rng = np.random.default_rng(0)
    el = np.deg2rad(rng.uniform(-7, 12, 20000))
    az = rng.uniform(-0.8, 0.8, 20000)
    hit = np.stack([np.full(20000, 12.0), 12.0 * np.tan(az), 12.0 * np.tan(el) / np.cos(az)], 1)
    hit = hit[hit[:, 2] < np.where(hit[:, 1] < 0, 20.0, 0.5)]  # only the wall returns (the sky returns nothing)
    lidar = LidarSweeps([hit.astype(np.float32)] * frames, np.zeros((frames, 3)))
    cam = CameraSequence("cam", width, height, K, c2w, paths, np.arange(frames) * 0.1)
    train, test = holdout_split(frames, 0)
    scene = SceneData("wall", [cam], np.arange(frames) * 0.1, np.arange(frames), train, test, lidar, []).validate()
    return scene, wall, p


def test_sky_mask_is_not_trusted_above_the_lidar_limit_or_on_texture(tmp_path):
    scene, wall, p = _wall_scene(tmp_path)
    masks = SkyMasks(scene, ImageCache(), torch.device("cpu"))
    sky, trusted = masks.get(View(0, 0))[..., 0].numpy() > 0.5, masks.trusted(View(0, 0))[..., 0].numpy() > 0.5
    # the heuristic's known limit: the tall wall above the LiDAR's reach is taken for sky ...
    reach = np.hypot(12.0, p[..., 1]) * np.tan(np.deg2rad(12.0))  # the highest LiDAR return on the wall
    tall_above_reach = wall & (p[..., 1] < -1.0) & (p[..., 2] > reach + 0.5)
    assert tall_above_reach.sum() > 100 and sky[tall_above_reach].mean() > 0.95
    # ... and that "sky" is not trusted
    assert not trusted[tall_above_reach].any()
    # open sky over the low wall, away from its edge and from the tall wall's columns: trusted
    open_sky = ~wall & (p[..., 1] > 1.5) & (p[..., 2] > 2.0)
    assert open_sky.sum() > 100 and sky[open_sky].all() and trusted[open_sky].mean() > 0.95
    # non-sky labels are always trusted; the low wall's textured edge with the sky is not
    assert trusted[~sky].all()
    edge = sky & ~wall & (p[..., 1] > 1.5) & (p[..., 2] < 1.0)  # within 3 px of the wall top
    assert edge.sum() > 0 and not trusted[edge].any()


def test_opacity_loss_skips_untrusted_sky_pixels():
    from omnire.losses import LossContext, opacity_mask_loss

    g = torch.Generator().manual_seed(0)
    alpha = torch.rand(8, 10, 1, generator=g)
    sky = (torch.rand(8, 10, 1, generator=g) > 0.5).float()
    trusted = (torch.rand(8, 10, 1, generator=g) > 0.3).float()
    scene = torch.ones(8, 10, 1)
    scene[0] = 0.0
    ctx = LossContext(alpha.expand(-1, -1, 3), alpha, alpha, alpha.expand(-1, -1, 3), sky_mask=sky,
                      sky_trusted=trusted, scene_pixels=scene)
    keep = (trusted * scene).bool()[..., 0]
    a, target = alpha[..., 0][keep].double(), 1 - sky[..., 0][keep].double()
    expected = -(target * a.log() + (1 - target) * (1 - a).log()).mean()
    assert abs(float(opacity_mask_loss(ctx)) - float(expected)) < 1e-5


def _ray_hits_box(o, d, pose, size):
    """(N,) camera depth where rays o + t d (d with unit camera z) enter the box, inf if they miss."""
    d_l, o_l = d @ pose[:3, :3], (o - pose[:3, 3]) @ pose[:3, :3]
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-size / 2 - o_l) / d_l, (size / 2 - o_l) / d_l
    t_in, t_out = np.nanmax(np.minimum(t1, t2), -1), np.nanmin(np.maximum(t1, t2), -1)
    return np.where(t_out >= np.maximum(t_in, 0.0), np.maximum(t_in, 0.0), np.inf)


def test_lidar_finds_occluders_without_a_box(tmp_path):
    """A pedestrian box 10 m away, its lower left behind a hedge (x = 8, no box): the box
    pixels the hedge hides leave the human mask, the rest stays; LiDAR returns (cast from the
    camera) on the hedge, the person and a far wall are all the masks get."""
    from omnire.data.scene import ActorTrack, CameraSequence, LidarSweeps, SceneData

    W, H = 96, 64
    K = np.array([[120.0, 0, W / 2], [0, 120.0, H / 2], [0, 0, 1]])
    c2w = np.eye(4)
    c2w[:3, :3] = LOOK_X
    pose = np.eye(4)
    pose[:3, 3] = [10.0, 0.0, -0.2]
    size = np.array([1.0, 2.0, 2.2])
    hedge_x, hedge_y, hedge_z = 8.0, (0.0, 3.0), (-2.0, -0.3)  # covers y >= 0, z <= -0.3

    def hedge_depth(d):  # camera depth of a ray's hit on the hedge patch (inf if it misses)
        t = hedge_x / d[:, 0]
        p = d * t[:, None]
        hit = (p[:, 1] >= hedge_y[0]) & (p[:, 1] <= hedge_y[1]) & (p[:, 2] >= hedge_z[0]) & (p[:, 2] <= hedge_z[1])
        return np.where(hit, t, np.inf)

    # LiDAR: 6000 random rays from the camera over its field of view, the nearest hit of each
    rng = np.random.default_rng(0)
    d = np.stack([rng.uniform(0, W, 6000), rng.uniform(0, H, 6000)], 1)
    d = np.stack([(d[:, 0] - K[0, 2]) / K[0, 0], (d[:, 1] - K[1, 2]) / K[1, 1], np.ones(6000)], -1) @ LOOK_X.T
    t = np.minimum(np.minimum(hedge_depth(d), _ray_hits_box(np.zeros(3), d, pose, size * 0.9)), 20.0 / d[:, 0])
    points = (d * t[:, None]).astype(np.float32)

    track = ActorTrack("ped", "Pedestrian", "human", pose[None], size, np.ones(1, bool))
    cam = CameraSequence("cam", W, H, K, c2w[None], [tmp_path / "x.png"], np.zeros(1))

    def human_mask(lidar):
        scene = SceneData("hedge", [cam], np.zeros(1), np.zeros(1, int), np.zeros(1, int), np.zeros(0, int), lidar,
                          [track])
        return DynamicMasks(scene, ImageCache(), torch.device("cpu")).get(View(0, 0), "human")[..., 0].numpy() > 0.5

    v, u = np.mgrid[0:H, 0:W] + 0.5
    rays = (np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1) @ LOOK_X.T).reshape(-1, 3)
    box_t = _ray_hits_box(np.zeros(3), rays, pose, size).reshape(H, W)
    hidden = np.isfinite(box_t) & (hedge_depth(rays).reshape(H, W) < box_t)
    seen = np.isfinite(box_t) & ~hidden
    assert hidden.sum() > 100 and seen.sum() > 100

    boxes_only = human_mask(LidarSweeps([None], np.full((1, 3), np.nan)))
    assert boxes_only[hidden].all()  # without LiDAR the box stands where the hedge hides it
    with_lidar = human_mask(LidarSweeps([points], np.zeros((1, 3))))
    assert with_lidar[hidden].mean() < 0.15  # the hidden part leaves the mask (boundary pixels may stay)
    assert with_lidar[seen].mean() > 0.9  # the visible part stays
