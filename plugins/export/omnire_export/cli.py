"""``omnire export``: a trained run as standard 3DGS PLY files."""
from __future__ import annotations

import dataclasses
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire.api import (
    ConfigError,
    RunDirectory,
    UserError,
    check_location,
    check_output_dir,
    staged_directory,
    staged_files,
)


@dataclasses.dataclass
class ExportArgs:
    """Export a trained scene at a moment as standard 3DGS PLY (binary little-endian): the
    whole scene composed at --frame, or each node and actor with a pose file (--per-node), or
    a numbered sequence (--frames all); the sky's environment map is written beside it."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    output: Path
    """The PLY file to write (e.g. scene.ply); with --per-node, a folder."""
    frame: float = 0.0
    """Frame to export (0-based within the loaded range; fractional frames interpolate)."""
    frames: Optional[str] = None
    """Export several frames instead of --frame: 'all', 'start:stop[:step]' or 'f1,f2,...'.
    Files are numbered <stem>_<frame>.ply (folders frame_<frame>/ with --per-node)."""
    per_node: bool = False
    """Write every node and actor in its own PLY (actors in their box frame) plus poses.json."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the newest intact one in the run directory)."""
    overwrite: bool = False
    """Replace existing output files."""
    chunk_rows: int = 1 << 16
    """Gaussians converted at a time (memory use beyond the parameters is about 250 bytes each)."""


class ExportError(UserError):
    """The export cannot be written as asked."""


EXPORT_TOOL = "omnire export"
EXPORT_KINDS = (".ply", ".png", ".json")
"""What omnire export writes into a --per-node folder (what --overwrite may replace)."""


def check_output(args: ExportArgs) -> None:
    """Refuse outputs that exist (unless --overwrite) or have the wrong form, before loading;
    nothing is written into the run directory or its dataset, and --overwrite replaces a
    --per-node folder only when it is omnire export's own (omnire/io/outputs.py)."""
    out = args.output
    if args.chunk_rows <= 0:
        raise ConfigError(f"--chunk-rows {args.chunk_rows}: must be positive")
    protect = (args.run_dir, RunDirectory(args.run_dir).data_path())
    if args.per_node:
        check_output_dir(out, EXPORT_TOOL, overwrite=args.overwrite, kinds=EXPORT_KINDS, protect=protect)
        return
    check_location(out, "--output", protect)
    if out.suffix.lower() != ".ply":
        raise ExportError(f"--output {out}: expected a .ply file name (or use --per-node for a folder)")
    if out.is_dir():
        raise ExportError(f"--output {out}: is a folder; expected a .ply file name")
    if args.frames is None and out.exists() and not args.overwrite:
        raise ExportError(f"--output {out}: exists (use --overwrite to replace it)")


def main(argv: list[str], plugins) -> int:
    import torch
    from rich.progress import Progress

    from omnire.command_api import output_console
    from omnire_export.export import export, parse_frames
    from omnire_export.loading import load_reconstruction

    args = tyro.cli(ExportArgs, args=argv, prog="omnire export")
    check_output(args)
    torch.set_num_threads(max(1, min(torch.get_num_threads(), 4)))
    t0 = time.perf_counter()
    recon = load_reconstruction(args.run_dir, plugins, args.checkpoint)
    F = recon.scene.num_frames
    if args.frames is not None:
        frames = parse_frames(args.frames, F)
    else:
        if not 0 <= args.frame <= F - 1:
            raise ConfigError(f"--frame {args.frame}: outside the scene's frames 0..{F - 1}")
        frames = [float(args.frame)]
    sequence = args.frames is not None
    if sequence and not args.per_node and not args.overwrite:
        from omnire_export.export import frame_label

        stem = args.output.name[:-4]
        clash = [args.output.parent / f"{stem}_{frame_label(f, F)}.ply" for f in frames]
        clash = [p for p in clash if p.exists()]
        if clash:
            raise ExportError(f"{clash[0]}: exists (use --overwrite to replace the sequence)")
    console = output_console()
    # written into staging first and moved into place when complete: a failed write leaves nothing
    staging = staged_directory(args.output, EXPORT_TOOL) if args.per_node else staged_files(args.output.parent)
    with Progress(console=console, transient=True, disable=len(frames) < 2) as bar, staging as folder:
        task = bar.add_task("export", total=len(frames))
        target = folder if args.per_node else folder / args.output.name
        written = export(recon, frames, target, args.per_node, sequence, args.chunk_rows,
                         progress=lambda _f: bar.advance(task))
    plys = [p for p in written.files if p.suffix == ".ply"]
    others = [p for p in written.files if p.suffix != ".ply"]
    also = f"; also {', '.join(sorted({p.name for p in others}))}" if others else ""
    console.print(f"wrote {len(plys)} PLY file(s), {written.count} Gaussians in total, to {args.output} "
                  f"in {time.perf_counter() - t0:.1f} s{also}", highlight=False)
    return 0
