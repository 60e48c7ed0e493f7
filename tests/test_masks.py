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
