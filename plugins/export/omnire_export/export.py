"""Writing a reconstructed scene at a moment: one PLY of the whole scene, or one PLY per node
and actor with a pose file; the sky's environment map as an equirectangular image.

Layouts (``<out>`` is the ``--output`` path):

- whole scene: ``<out>`` (e.g. ``scene.ply``); ``<stem>.<sky node>.png`` beside it.
- sequence (``--frames``): ``<stem>_<frame>.ply`` for each frame (zero-padded), the sky once.
- per node (``--per-node``): ``<out>/`` holds ``<node>.ply`` for every non-actor node (world
  frame), ``<node>/<track id>.ply`` for every actor present (its box frame at the moment),
  ``poses.json`` and ``<sky node>.png``; with ``--frames`` one such folder per frame,
  ``<out>/frame_<frame>/``.

``poses.json`` (per node): ``{"format", "frame", "seconds", "sh_degree", "environment",
"parts": [...]}``; ``parts`` lists every file in the order of the whole-scene export, each
``{"file", "node", "count"}`` plus, for actors, ``{"track_id", "class_name", "category",
"rigid", "pose", "poses"}``: ``pose`` places the actor at the exported moment, ``poses``
lists ``{"frame", "seconds", "R", "t", "quat_wxyz"}`` for every recorded frame the actor is
present (box-to-world: world = R x + t, Gaussian rotations q(R) * q). ``rigid`` is true when
the actor's box-frame Gaussians are the same at every moment (then the file and ``poses``
animate it); pedestrians and deformable actors change shape, so their file is their shape
at the exported moment only.
"""
from __future__ import annotations

import dataclasses
import json
import math
import re
from pathlib import Path
from typing import Callable, Iterable, Optional

import torch

from omnire.api import ActorNode, SceneTime, atomic_write_text, write_png
from omnire_export.compose import Part, Pose, local_state, scene_parts
from omnire_export.ply import PlyStreamWriter, pack_rows

DEFAULT_CHUNK_ROWS = 1 << 16
"""Gaussians converted and written at a time (~16 MB of rows)."""

POSES_FORMAT = "omnire-export-poses/1"

ENVIRONMENT_LAYOUT = ("equirectangular: rows from elevation +90 to -90 degrees, columns from azimuth -180 to "
                      "+180 degrees about the world +z axis (azimuth 0 = +x, +90 = +y); 16-bit PNG, linear "
                      "values as the model composites them")


@dataclasses.dataclass
class Written:
    """What one export wrote: files and Gaussian count."""

    files: list[Path]
    count: int


def write_parts(path: Path, parts: Iterable[Part], sh_degree: int, chunk_rows: int = DEFAULT_CHUNK_ROWS,
                comments: tuple[str, ...] = (), lidar: bool = False) -> int:
    """Stream ``parts`` (world frame) into one PLY at ``path``; returns the vertex count.
    ``lidar``: the parts carry LiDAR features, written as ``omnire_export.ply.LIDAR_PROPERTIES``."""
    with PlyStreamWriter(path, comments, lidar) as out:
        for part in parts:
            for start in range(0, len(part), chunk_rows):
                out.write(packed(part.arrays(start, min(len(part), start + chunk_rows)), sh_degree, lidar))
        return out.count


def write_local(path: Path, part: Part, sh_degree: int, chunk_rows: int = DEFAULT_CHUNK_ROWS,
                comments: tuple[str, ...] = ()) -> int:
    """One part in its own frame (box frame for an actor) as a PLY at ``path`` (with
    ``omnire_export.ply.LIDAR_PROPERTIES`` when it has LiDAR features)."""
    lidar = part.lidar is not None
    with PlyStreamWriter(path, comments, lidar) as out:
        for start in range(0, len(part), chunk_rows):
            out.write(packed(part.local_arrays(start, min(len(part), start + chunk_rows)), sh_degree, lidar))
        return out.count


def packed(a: dict, sh_degree: int, lidar: bool):
    """PLY rows of :meth:`Part.arrays` output ``a``; ``lidar``: with its LiDAR features
    (refused when the part has none, rather than writing a made-up value)."""
    if lidar and "lidar" not in a:
        raise ValueError("a part without LiDAR features in a PLY with LiDAR properties")
    return pack_rows(a["means"], a["quats"], a["scales"], a["opacities"], a["sh0"], a["shN"], sh_degree,
                     a["lidar"] if lidar else None)


def environment_maps(recon) -> dict[str, torch.Tensor]:
    """(H, W, 3) equirectangular maps of the environment nodes that offer one (by node name)."""
    return {name: node.environment_map() for name, node in recon.environment_nodes().items()
            if hasattr(node, "environment_map")}


def write_environment(recon, folder: Path, stem: Optional[str]) -> list[Path]:
    """Each environment map as ``<folder>/<stem>.<node>.png`` (``<node>.png`` without a stem),
    16-bit (the map is a learned texture in [0, 1]; 8 bits would band smooth skies)."""
    written = []
    for name, env in environment_maps(recon).items():
        path = folder / (f"{stem}.{name}.png" if stem else f"{name}.png")
        write_png(path, (env.detach().cpu().clamp(0, 1) * 65535.0 + 0.5).floor(), bits=16)
        written.append(path)
    return written


def safe_name(text: str) -> str:
    """A file name for a track id (other characters become ``_``)."""
    name = re.sub(r"[^A-Za-z0-9._-]", "_", text).strip(".")
    return name or "_"


def frame_label(frame: float, num_frames: int) -> str:
    """Zero-padded frame number for file names (fractional frames keep their decimals)."""
    width = max(4, len(str(num_frames - 1)))
    if float(frame).is_integer():
        return f"{int(frame):0{width}d}"
    whole, frac = f"{frame:.6f}".rstrip("0").split(".")
    return f"{int(whole):0{width}d}.{frac}"


def header_comments(recon, t: SceneTime) -> tuple[str, ...]:
    info, run = recon.run_info, recon.run_dir
    out = [f"omnire export: frame {t.frame} ({t.seconds:.6f} s), step {recon.step}, sh degree {recon.sh_degree()}"]
    if info is not None:
        out.append(f"method {info.method}, dataparser {info.dataparser}, run {run.path if run is not None else None}")
        attribution = info.extra.get("attribution")
        if attribution:
            out.append(" ".join(str(attribution).split()))
    return tuple(out)


@torch.no_grad()
def export_scene(recon, t: SceneTime, path: Path, chunk_rows: int = DEFAULT_CHUNK_ROWS) -> int:
    """The whole scene at ``t`` (background, actors at their poses, pedestrians skinned) as
    one PLY at ``path``; returns the Gaussian count. Streams: at most ``chunk_rows`` rows
    are converted at a time."""
    return write_parts(path, scene_parts(recon, t, chunk_rows), recon.sh_degree(), chunk_rows,
                       header_comments(recon, t), lidar=recon.renders_lidar)


def recorded_poses(recon, node: ActorNode) -> dict[int, list[dict]]:
    """Per instance of ``node``: its pose at every recorded frame where it is present."""
    poses: dict[int, list[dict]] = {}
    for f in range(recon.scene.num_frames):
        t = recon.time(f)
        state = node.state_at(t)
        for k, i in enumerate(state.ids.tolist()):
            pose = Pose.from_rt(state.R[k].cpu().numpy(), state.t[k].cpu().numpy())
            poses.setdefault(int(i), []).append({"frame": f, "seconds": t.seconds, **pose.to_json()})
    return poses


def is_rigid(node: ActorNode, part: Part, t: SceneTime, recon) -> bool:
    """True when the actor's box-frame Gaussians at ``t`` equal those at the recorded frame
    where it is present that lies farthest from ``t`` (the same at every moment for a
    shape that does not change)."""
    present = node.poses.present[part.instance].nonzero().flatten().tolist()
    others = [f for f in present if f != t.frame]
    if not others:
        return True
    far = max(others, key=lambda f: abs(f - t.frame))
    t2 = recon.time(far)
    state = node.state_at(t2)
    sel = (state.ids == part.instance).nonzero().flatten()
    out = node.gaussians_for(local_state(state, sel), t2)
    if out is None or len(out.gaussians) != len(part):
        return False
    return all(torch.equal(getattr(out.gaussians, k), getattr(part.gaussians, k)) for k in
               ("means", "quats", "scales", "opacities", "sh0", "shN"))


@torch.no_grad()
def export_per_node(recon, t: SceneTime, folder: Path, chunk_rows: int = DEFAULT_CHUNK_ROWS,
                    write_sky: bool = True) -> Written:
    """Every node and actor at ``t`` in its own PLY under ``folder`` plus ``poses.json`` (see
    the module docstring); the sky's map as ``<node>.png`` unless ``write_sky`` is False."""
    folder = Path(folder)
    scene, nodes, degree = recon.scene, recon.nodes, recon.sh_degree()
    tracks = {tr.track_id: tr for tr in scene.tracks}
    comments = header_comments(recon, t)
    files, entries, total = [], [], 0
    pose_tables: dict[str, dict[int, list[dict]]] = {}
    used_names: set[str] = set()
    for part in scene_parts(recon, t, chunk_rows):
        node = nodes[part.node]
        if part.pose is None:
            rel = f"{safe_name(part.node)}.ply"
            entry = {"file": rel, "node": part.node}
        else:
            base = f"{safe_name(part.node)}/{safe_name(part.track_id)}"
            rel, n = f"{base}.ply", 1
            while rel in used_names:  # two ids that map to one file name
                n += 1
                rel = f"{base}~{n}.ply"
            if part.node not in pose_tables:
                pose_tables[part.node] = recorded_poses(recon, node)
            track = tracks.get(part.track_id)
            entry = {"file": rel, "node": part.node, "track_id": part.track_id,
                     "class_name": track.class_name if track else None,
                     "category": track.category if track else None,
                     "size": [float(v) for v in track.size] if track is not None else None,
                     "rigid": is_rigid(node, part, t, recon),
                     "pose": part.pose.to_json(), "poses": pose_tables[part.node].get(part.instance, [])}
        used_names.add(rel)
        count = write_local(folder / rel, part, degree, chunk_rows, comments)
        entry["count"] = count
        total += count
        files.append(folder / rel)
        entries.append(entry)
    envs = write_environment(recon, folder, None) if write_sky else []
    manifest = {
        "format": POSES_FORMAT, "frame": t.frame, "seconds": t.seconds, "step": recon.step, "sh_degree": degree,
        "scene": scene.name, "num_frames": scene.num_frames,
        "environment": [{"file": p.name, "node": p.stem, "layout": ENVIRONMENT_LAYOUT} for p in envs],
        "parts": entries,
    }
    atomic_write_text(folder / "poses.json", manifest_json(manifest))
    return Written(files + envs + [folder / "poses.json"], total)


def manifest_json(manifest: dict) -> str:
    """``poses.json`` text: one line per part and per recorded pose (readable, compact)."""
    head = [f" {json.dumps(k)}: {json.dumps(v)}" for k, v in manifest.items() if k != "parts"]
    parts = []
    for part in manifest["parts"]:
        fields = {k: v for k, v in part.items() if k != "poses"}
        text = json.dumps(fields)
        if "poses" in part:
            poses = ",\n   ".join(json.dumps(p) for p in part["poses"])
            text = text[:-1] + ', "poses": [\n   ' + poses + "]}"
        parts.append("  " + text)
    return "{\n" + ",\n".join(head + [' "parts": [\n' + ",\n".join(parts) + "]"]) + "\n}\n"


def parse_frames(spec: str, num_frames: int) -> list[float]:
    """``all``, ``a:b`` / ``a:b:step`` (end exclusive, 0 <= a < b <= num_frames, step >= 1)
    or ``f1,f2,...`` (distinct, fractional allowed) -> frame positions. One rule: a frame or
    bound outside the scene's frames 0..num_frames-1 is refused, naming that range."""
    from omnire.api import ConfigError

    spec = spec.strip()
    last = num_frames - 1
    if spec == "all":
        return [float(f) for f in range(num_frames)]
    form = "expected 'all', 'start:stop[:step]' or a comma list of frames"
    try:
        if ":" in spec:
            parts = spec.split(":")
            if len(parts) > 3:
                raise ValueError
            start = int(parts[0]) if parts[0].strip() else 0
            stop = int(parts[1]) if parts[1].strip() else num_frames
            step = int(parts[2]) if len(parts) == 3 and parts[2].strip() else 1
            if step < 1:
                raise ConfigError(f"--frames {spec!r}: the step must be >= 1")
            if not (0 <= start < stop <= num_frames):
                raise ConfigError(f"--frames {spec!r}: start:stop must satisfy 0 <= start < stop <= {num_frames} "
                                  f"(the scene's frames are 0..{last}, stop exclusive)")
            frames = [float(f) for f in range(start, stop, step)]
        else:
            frames = [float(p) for p in spec.split(",") if p.strip()]
    except ValueError:
        raise ConfigError(f"--frames {spec!r}: {form}") from None
    bad = [f for f in frames if math.isnan(f) or not 0 <= f <= last]
    if bad or not frames:
        raise ConfigError(f"--frames {spec!r}: frames must lie in 0..{last} (got {bad or 'none'})")
    seen: set[float] = set()
    for f in frames:
        if f in seen:
            raise ConfigError(f"--frames {spec!r}: frame {f:g} is listed more than once")
        seen.add(f)
    return frames


def export(recon, frames: list[float], output: Path, per_node: bool, sequence: bool,
           chunk_rows: int = DEFAULT_CHUNK_ROWS, progress: Optional[Callable[[float], None]] = None) -> Written:
    """Export ``frames`` of ``recon`` to ``output`` in the layout the module docstring gives.
    ``sequence``: name outputs by frame even for a single frame."""
    output = Path(output)
    F = recon.scene.num_frames
    files, total = [], 0
    if per_node:
        for frame in frames:
            folder = output / f"frame_{frame_label(frame, F)}" if sequence else output
            done = export_per_node(recon, recon.time(frame), folder, chunk_rows, write_sky=not sequence)
            files += done.files
            total += done.count
            if progress:
                progress(frame)
        if sequence:
            files += write_environment(recon, output, None)
        return Written(files, total)
    stem = output.name[:-4] if output.name.lower().endswith(".ply") else output.name
    for frame in frames:
        path = output.parent / f"{stem}_{frame_label(frame, F)}.ply" if sequence else output
        total += export_scene(recon, recon.time(frame), path, chunk_rows)
        files.append(path)
        if progress:
            progress(frame)
    files += write_environment(recon, output.parent, stem)
    return Written(files, total)
