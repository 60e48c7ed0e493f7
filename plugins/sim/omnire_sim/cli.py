"""``omnire sim <run> --scenario FILE --output DIR``: render an edited scene to PNG frames
and an MP4 per camera, with a manifest of what was rendered.

Everything that can be wrong (the scenario, the run, asset runs, the camera path, the output
directory) is checked before the first pixel is rendered, so a bad scenario writes nothing.
Frames and videos are written into a hidden staging directory beside the output, which is
renamed into place when everything is done (with ``--overwrite`` the old output is replaced
only then, and only when it is omnire sim's own: omnire/io/outputs.py): an interrupted or
failed run leaves no partial output. Nothing is written into the run directory or its dataset.
"""
from __future__ import annotations

import contextlib
import dataclasses
import json
import time
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import tyro

from omnire.api import (
    DEFAULT_FRAME_CAP,
    ConfigError,
    Reconstruction,
    RunDirectory,
    UserError,
    atomic_write_text,
    check_fps,
    check_image_size,
    check_output_dir,
    recorded_sweep,
    sensor_path,
    staged_directory,
    sweep_points,
    write_png,
    write_point_cloud,
)
from omnire.command_api import CameraPath, Mp4Writer, file_path, interpolated_path, recorded_path
from omnire_sim.edits import CameraSpec, Scenario
from omnire_sim.engine import Simulation
from omnire_sim.scenario import check_against_scene, load_scenario


@dataclasses.dataclass
class SimArgs:
    """Render a reconstructed scene with edits (a scenario file) to images and videos."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    scenario: Path
    """Scenario file (TOML; see docs/simulation.md). An empty file renders the recorded scene."""
    output: Path
    """Output directory (refused when it exists, unless --overwrite)."""
    overwrite: bool = False
    """Replace an existing output directory (only once the new output is complete)."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the run's newest intact one)."""
    cameras: tuple[str, ...] = ()
    """Cameras to render (default: the scenario's, else all)."""
    fps: Optional[float] = None
    """Video frame rate (default: the scenario's [output] fps, else the camera path's rate)."""
    width: Optional[int] = None
    """Image width (with --height; default: the scenario's, else the dataset's)."""
    height: Optional[int] = None
    """Image height (with --width)."""
    depth: bool = False
    """Also write depth images (16-bit PNG, millimetres), as does [output] depth = true."""
    alpha: bool = False
    """Also write alpha (opacity) images (8-bit PNG), as does [output] alpha = true."""
    video: bool = True
    """Write an MP4 (H.264) per camera (--no-video: frames only; so does [output] video = false)."""
    frames: bool = True
    """Write PNG frames per camera (--no-frames: videos only; so does [output] frames = false)."""
    max_frames: int = 0
    """Render only the first N frames of the camera path (0 = all), e.g. for a preview."""
    frame_cap: int = DEFAULT_FRAME_CAP
    """Refuse camera paths of more frames than this (a guard against runaway requests; raise it for long paths)."""
    progress: bool = True
    """Show a progress bar."""
    lidar: bool = False
    """Also render the LiDAR at every frame of the path, with the scenario's edits: lidar/<index>.ply and .npz
    (omnire render --lidar's fields). The sensor rides its recorded path at the frame's scene time and fires the rays
    of the nearest recorded sweep (a lane shift of the cameras does not move it). Needs a run trained with
    --method.lidar.enabled."""


def build_path(scene, spec: CameraSpec, scenario: Scenario, cameras: tuple[str, ...] = (),
               size: Optional[tuple[int, int]] = None, frame_cap: int = DEFAULT_FRAME_CAP) -> CameraPath:
    """The scenario's camera path; errors name the [camera] table's line and field."""
    w = spec.where
    names = cameras or spec.cameras or None
    try:
        if spec.path == "recorded":
            path = recorded_path(scene, names, spec.frames, spec.fps, frame_cap)
        elif spec.path == "interpolated":
            path = interpolated_path(scene, spec.fps, names, spec.start, spec.end, frame_cap)
        else:
            path = file_path(scene, scenario.resolve_path(spec.file), names, spec.fps, frame_cap)
    except UserError as exc:
        field = {"recorded": "frames", "interpolated": "end", "file": "file"}[spec.path]
        raise w.error(field if field in dict(w.field_lines) else "path", str(exc)) from None
    size = size or ((spec.width, spec.height) if spec.width else None)
    if size:
        path = path.resized(*size)
    try:
        if spec.scene_time is not None:
            path = path.with_scene_time(scene, spec.scene_time)
        elif spec.scene_speed is not None:
            path = path.with_scene_speed(scene, spec.scene_speed)
    except UserError as exc:
        raise w.error("scene_time" if spec.scene_time is not None else "scene_speed", str(exc)) from None
    for shift in spec.lane_shifts:
        path = path.lane_shifted(shift.offset, shift.start, shift.end)
    return path


SIM_TOOL = "omnire sim"
SIM_KINDS = (".png", ".mp4", ".json", ".ply", ".npz")
"""What omnire sim writes into its output directory (what --overwrite may replace)."""


def check_output(output: Path, run_dir: Path, overwrite: bool) -> None:
    """Refuse an output that is, holds or lies inside the run directory or its dataset, and an
    existing one unless ``overwrite`` and it is omnire sim's own (omnire/io/outputs.py)."""
    check_output_dir(output, SIM_TOOL, overwrite=overwrite, kinds=SIM_KINDS,
                     protect=(run_dir, RunDirectory(run_dir).data_path()))


def sim_sweep(sim: Simulation, scene_time) -> np.ndarray:
    """The LiDAR point cloud (omnire.api.POINT_FIELDS) of the edited scene at ``scene_time``:
    the rays of the nearest recorded sweep, fired at the same offsets from ``scene_time`` as
    they were from their frame's, from the recorded sensor path, rendered with the edits."""
    recon = sim.recon
    scene = recon.scene
    have = [f for f in range(scene.num_frames) if scene.lidar.points[f] is not None]
    frame = min(have, key=lambda f: abs(float(scene.frame_timestamps[f]) - scene_time.seconds))
    sweep = recorded_sweep(scene, frame)
    sweep = dataclasses.replace(sweep, times=sweep.times + (scene_time.seconds - float(scene.frame_timestamps[frame])))
    path, sectors = sensor_path(scene), recon.method.lidar.sectors
    return sweep_points(recon.render_sweep(sweep, path, sectors, edits=sim), sweep, path, sectors)


def _summary(sim: Simulation) -> list[dict]:
    out = []
    for a in sim.actors:
        kind = "removed" if a.removed else ("inserted" if a.inserted else "edited")
        item = {"id": a.key, "kind": kind, "node": a.node_name}
        if a.inserted:
            item["run"] = str(a.owner.run_dir.path) if a.owner.run_dir is not None else None
            item["track"] = a.node.track_ids[a.instance]
        if a.motion:
            item["motion"] = a.motion
        out.append(item)
    return out


def run_sim(args: SimArgs, plugins, argv: Optional[list[str]] = None) -> Path:
    """Everything ``omnire sim`` does; returns the output directory."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    from omnire.command_api import output_console

    scenario = load_scenario(args.scenario)
    if (args.width is None) != (args.height is None):
        raise ConfigError("--width and --height: give both or neither")
    if args.width is not None:
        check_image_size(args.width, args.height, "--width/--height")
    if args.fps is not None:
        check_fps(args.fps, "--fps")
    if args.max_frames < 0:
        raise ConfigError(f"--max-frames {args.max_frames}: must be >= 0")
    if args.frame_cap < 1:
        raise ConfigError(f"--frame-cap {args.frame_cap}: must be >= 1")
    check_output(args.output, args.run_dir, args.overwrite)
    recon = Reconstruction.from_run(args.run_dir, plugins, args.checkpoint)
    if args.lidar and not recon.renders_lidar:
        raise ConfigError(f"--lidar: the run {args.run_dir} learned no LiDAR (train it with --method.lidar.enabled "
                          "on a scene with LiDAR)")
    check_against_scene(scenario, recon.scene)
    sim = Simulation(recon, scenario, plugins)
    size = (args.width, args.height) if args.width is not None else None
    path = build_path(recon.scene, scenario.camera, scenario, args.cameras, size, args.frame_cap)
    n_frames = len(path) if args.max_frames == 0 else min(args.max_frames, len(path))
    want = dataclasses.replace(scenario.output, depth=args.depth or scenario.output.depth,
                               alpha=args.alpha or scenario.output.alpha, video=args.video and scenario.output.video,
                               frames=args.frames and scenario.output.frames)
    if not (want.video or want.frames):
        raise ConfigError("nothing to write: both frames and video are switched off")
    fps = args.fps or want.fps or path.fps

    output = args.output
    console = output_console(stderr=True)
    frames_meta = []
    t_render = 0.0
    with staged_directory(output, SIM_TOOL) as staging:
        with contextlib.ExitStack() as stack, torch.no_grad():
            videos = {}
            if want.video:
                for name in path.names:
                    videos[name] = stack.enter_context(Mp4Writer(staging / f"{name}.mp4", fps, want.crf))
            progress = stack.enter_context(Progress(
                TextColumn("[bold]sim[/] {task.description}"), BarColumn(), MofNCompleteColumn(), TextColumn("frames"),
                TimeElapsedColumn(), TimeRemainingColumn(), console=console, disable=not args.progress))
            task = progress.add_task(f"{len(path.names)} camera(s) -> {output}", total=n_frames)
            for i in range(n_frames):
                scene_time = path.time(recon.scene, i)
                entry = {"index": i, "path_seconds": float(path.seconds[i]),
                         "scene_seconds": float(scene_time.seconds - recon.scene.frame_timestamps[0]),
                         "scene_frame": float(scene_time.frame), "cameras": {}}
                t0 = time.perf_counter()
                results = sim.render_cameras([path.camera(c, i, recon.device) for c in range(len(path.names))],
                                             scene_time)
                t_render += time.perf_counter() - t0
                for c, (name, result) in enumerate(zip(path.names, results)):
                    cam_entry = {"cam_to_world": np.round(path.cam_to_world[c, i], 9).tolist()}
                    if want.frames:
                        rel = f"{name}/{i:05d}.png"
                        write_png(staging / rel, result.rgb)
                        cam_entry["image"] = rel
                    if want.depth:
                        rel = f"{name}/depth/{i:05d}.png"
                        write_png(staging / rel, result.depth * 1000.0, bits=16)
                        cam_entry["depth"] = rel
                    if want.alpha:
                        rel = f"{name}/alpha/{i:05d}.png"
                        write_png(staging / rel, result.alpha)
                        cam_entry["alpha"] = rel
                    if want.video:
                        videos[name].append(result.rgb)
                    entry["cameras"][name] = cam_entry
                if args.lidar:
                    rel = f"lidar/{i:05d}"
                    write_point_cloud(staging / rel, sim_sweep(sim, scene_time), f"omnire sim: path frame {i}")
                    entry["lidar"] = [f"{rel}.ply", f"{rel}.npz"]
                frames_meta.append(entry)
                progress.update(task, advance=1)
        manifest = {
            "command": ["omnire", "sim", *(argv or [])],
            "run": str(args.run_dir.resolve()),
            "checkpoint_step": recon.step,
            "method": recon.run_info.method if recon.run_info is not None else None,
            "scene": recon.scene.name,
            "attribution": recon.scene.attribution,
            "scenario": str(args.scenario.resolve()),
            "scenario_text": args.scenario.read_text(encoding="utf-8"),
            "actors": _summary(sim),
            "camera_path": {"kind": scenario.camera.path, "cameras": list(path.names),
                            "sizes": [list(s) for s in path.sizes], "frames": n_frames, "fps": path.fps,
                            "scene_seconds": [float(f["scene_seconds"]) for f in frames_meta]},
            "outputs": {"frames": want.frames, "depth": want.depth, "alpha": want.alpha, "depth_units": "millimetres",
                        "lidar": args.lidar,
                        "videos": {n: f"{n}.mp4" for n in path.names} if want.video else {},
                        "video_fps": fps if want.video else None, "video_codec": "h264 (libx264, yuv420p)",
                        "crf": want.crf},
            "frames": frames_meta,
            "render_seconds": round(t_render, 3),
            "render_fps": round(n_frames * len(path.names) / t_render, 3) if t_render > 0 else None,
        }
        atomic_write_text(staging / "manifest.json", json.dumps(manifest, indent=1) + "\n")
    console.print(f"wrote {n_frames} frame(s) x {len(path.names)} camera(s) to {output} "
                  f"({manifest['render_fps']} images/s rendered)")
    return output


def main(argv: list[str], plugins) -> int:
    args = tyro.cli(SimArgs, args=argv, prog="omnire sim")
    torch.set_num_threads(max(1, torch.get_num_threads()))
    run_sim(args, plugins, argv)
    return 0
