"""``omnire synth <preset> <out dir> [--flags]``: generate a synthetic scene with ground truth."""
from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Annotated, Literal

import tyro

from omnire.api import Plugins, UserError
from omnire_synthetic.generate import SynthOptions, generate

Preset = Literal["urban", "highway", "crowd", "empty"]


@dataclasses.dataclass
class SynthCommand:
    """Generate a synthetic driving scene (processed-scene format plus ground_truth.npz/json)."""

    preset: tyro.conf.Positional[Preset]
    """urban (mixed), highway (vehicles only), crowd (many pedestrians crossing), empty (static street)."""
    out: tyro.conf.Positional[Path]
    """Output scene folder: new, empty, or a previous synthetic scene (which is replaced)."""
    options: Annotated[SynthOptions, tyro.conf.OmitArgPrefixes] = dataclasses.field(default_factory=SynthOptions)
    """Generator options."""
    tiny: bool = False
    """Test size: 8 frames at 72x48 (overrides --frames, --width, --height)."""
    format: str = "processed"
    """On-disk layout: processed (the reference implementation's), or a dataset's own layout
    from a registered scene writer (``omnire plugins`` lists them, e.g. waymo, nuscenes)."""


def main(argv: list[str], plugins: Plugins) -> int:
    """``omnire synth``; ``plugins``: the CLI's loaded plugins (the scene writers of --format)."""
    cmd = tyro.cli(SynthCommand, args=argv, prog="omnire synth")
    if cmd.format != "processed":
        writer = plugins.scene_writers.get(cmd.format)  # unknown format: RegistryError naming the known ones
        return _generate_and_convert(cmd, writer)
    return _generate(cmd, cmd.out)


def _generate_and_convert(cmd: SynthCommand, writer) -> int:
    """Generate in the processed layout in a temporary folder beside ``cmd.out``, then let
    ``writer`` write the dataset's own layout into ``cmd.out`` (new or empty)."""
    import shutil
    import tempfile

    out = Path(cmd.out)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise UserError(f"{out}: exists and is not an empty folder; {cmd.format} scenes are written into a new one")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".synth-", dir=out.parent) as tmp:
        code = _generate(cmd, Path(tmp) / "processed")
        staging = Path(tmp) / "converted"
        staging.mkdir()
        writer.write(Path(tmp) / "processed", staging)
        if out.exists():
            out.rmdir()
        shutil.move(str(staging), str(out))  # same file system: a rename, never a half-written scene
    return code


def _generate(cmd: SynthCommand, out: Path) -> int:
    opts = cmd.options
    if cmd.tiny:
        opts = dataclasses.replace(opts, frames=8, width=72, height=48)
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    console = Console()
    with Progress(TextColumn("[bold]synth[/] {task.description}"), BarColumn(), TextColumn("{task.completed}/{task.total}"),
                  TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task(f"{cmd.preset} -> {out}", total=opts.frames)
        summary = generate(out, cmd.preset, opts, progress=lambda done, total: bar.update(task, completed=done))
    sec = summary["seconds"]
    console.print(
        f"wrote {summary['frames']} frames x {summary['cameras']} cameras ({summary['size'][0]}x{summary['size'][1]}), "
        f"{summary['actors']} actors ({summary['pedestrians']} pedestrians), "
        f"~{summary['lidar_points_mean']:.0f} LiDAR points/frame to {summary['out']} in {sec['total']:.1f} s "
        f"(render {sec['render']:.1f}, lidar {sec['lidar']:.1f}, write {sec['write']:.1f})"
    )
    return 0
