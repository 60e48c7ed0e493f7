"""An episode as a video: per step, the rendered cameras side by side above a bird's-eye
view (the route and its corridor, the actors' boxes, the ego's box and path so far; a
collided actor in red), 10 frames per second of scene time."""
from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from omnire.command_api import Mp4Writer
from omnire_serve.boxes import footprint, footprint_of


def bird_view(info: dict, trail: np.ndarray, corridor, ego_size, width: int, height: int,
              metres: float = 60.0) -> np.ndarray:
    """(height, width, 3) uint8: ``metres`` across, centred ahead of the ego, heading up."""
    img = Image.new("RGB", (width, height), (24, 24, 28))
    draw = ImageDraw.Draw(img)
    ego = info["ego"]
    c, s = np.cos(ego["yaw"]), np.sin(ego["yaw"])
    scale = width / metres
    centre = np.array([ego["x"], ego["y"]]) + np.array([c, s]) * metres * 0.25 * height / width

    def px(xy: np.ndarray) -> list[tuple[float, float]]:
        d = np.atleast_2d(xy) - centre
        fwd, left = d @ np.array([c, s]), d @ np.array([-s, c])
        return list(zip(width / 2 - left * scale, height / 2 - fwd * scale))

    normals = np.stack([-np.sin(_headings(corridor.xy)), np.cos(_headings(corridor.xy))], 1)
    draw.line(px(corridor.xy + normals * corridor.left[:, None]), fill=(90, 90, 110), width=1)
    draw.line(px(corridor.xy - normals * corridor.right[:, None]), fill=(90, 90, 110), width=1)
    draw.line(px(corridor.xy), fill=(70, 130, 70), width=1)
    hit = (info.get("collided_with") or {}).get("id")
    for b in info["actors"]:
        colour = (230, 50, 50) if b["id"] == hit else (230, 200, 60) if b["category"] == "vehicle" else (80, 180, 240)
        draw.polygon(px(footprint_of(np.asarray(b["pose"]), np.asarray(b["size"]))), outline=colour)
    if len(trail) > 1:
        draw.line(px(trail), fill=(255, 255, 255), width=2)
    draw.polygon(px(footprint([ego["x"], ego["y"]], ego["yaw"], ego_size[0], ego_size[1])), fill=(40, 200, 120))
    draw.text((4, 4), f"t {info['t']:.1f} s  {ego['speed']:.1f} m/s  {info['event'] or ''}", fill=(255, 255, 255))
    return np.asarray(img)


def _headings(xy: np.ndarray) -> np.ndarray:
    d = np.diff(xy, axis=0)
    h = np.arctan2(d[:, 1], d[:, 0])
    return np.append(h, h[-1])


def write_episode_video(path: Path, frames: list[dict], infos: list[dict], corridor, ego_size,
                        fps: float = 10.0) -> None:
    """``frames``: per step the observation (camera name -> (H, W, 3) uint8)."""
    with Mp4Writer(path, fps) as video:
        trail = []
        for obs, info in zip(frames, infos):
            trail.append([info["ego"]["x"], info["ego"]["y"]])
            cams = [obs[n] for n in obs]
            h = max(im.shape[0] for im in cams)
            row = np.concatenate([np.pad(im, ((0, h - im.shape[0]), (0, 0), (0, 0))) for im in cams], axis=1)
            bev = bird_view(info, np.asarray(trail), corridor, ego_size, row.shape[1], max(240, row.shape[1] // 3))
            video.append(np.concatenate([row, bev], axis=0))
