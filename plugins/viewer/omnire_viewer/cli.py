"""``omnire view <run> [--scenario FILE.toml]``: the trained scene, or a simulation of it, in
the browser."""
from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import time
from pathlib import Path
from typing import Optional

import tyro

from omnire_viewer.app import ViewerError


@dataclasses.dataclass
class ViewArgs:
    """Show a trained scene in the browser (viser): Gaussians drawn by the browser, a time
    slider, per-node and per-actor toggles, the dataset cameras, actor selection and edits,
    and server renders with the real rasterizer. With --scenario, the scene as `omnire sim`
    would render it (removals, moves, trajectories, stops, inserted actors, pedestrian motions
    following the time slider)."""

    run_dir: tyro.conf.Positional[Path]
    """Run directory written by omnire train."""
    host: str = "127.0.0.1"
    """Address to listen on (0.0.0.0: every interface). Any address other machines can reach
    asks every client for a token (docs/viewer.md)."""
    token: Optional[str] = None
    """The token clients must give (default: $OMNIRE_VIEW_TOKEN, else a new random one when
    --host is not a loopback address; none on loopback)."""
    port: int = 8080
    """Port to listen on (0: any free port)."""
    checkpoint: Optional[Path] = None
    """Checkpoint file (default: the newest intact one in the run directory)."""
    scenario: Optional[Path] = None
    """Scenario file (TOML, the format of omnire sim, docs/simulation.md): show the simulated
    scene. Its [camera] and [output] tables are not used (the browser is the camera)."""
    frame: float = 0.0
    """Frame shown first."""
    max_gaussians: int = 3_000_000
    """Gaussians of non-actor nodes sent to the browser at most (a uniform subsample above;
    server renders use all)."""
    sky_splats: int = 10_000
    """Splats of the browser's sky shell (0: no sky in the browser view)."""
    device: Optional[str] = None
    """Torch device for loading and server renders (default: the run's)."""
    seconds: float = 0.0
    """Stop after this many seconds (0: run until Ctrl-C)."""


def check_run_dir(run_dir: Path, checkpoint: Optional[Path]) -> None:
    """Fail early, before any port is opened or data read, when there is nothing to show."""
    from omnire.api import RunDirectory

    if checkpoint is not None:
        if not Path(checkpoint).is_file():
            raise ViewerError(f"--checkpoint {checkpoint}: no such file")
        return
    if not run_dir.is_dir():
        raise ViewerError(f"{run_dir}: no such run directory")
    run = RunDirectory(run_dir)
    run.read_info()  # a clear error when run.json is missing or malformed
    if not run.checkpoints():
        raise ViewerError(f"{run_dir}: no checkpoint to show (checkpoints/step-*.pt is empty: the run has not saved "
                          "one yet; wait for the first, or watch training live with --trainer.observers viewer)")


@contextlib.contextmanager
def nesting_guard(path: Path):
    """Report a TOML / JSON input nested deeper than Python's parsers go (a RecursionError)
    as one line naming ``path``."""
    try:
        yield
    except RecursionError:
        raise ViewerError(f"{path}: nested too deeply to read (lists or tables thousands of levels deep; "
                          "not a file omnire wrote)") from None


def check_args(args: ViewArgs) -> None:
    """Refuse option values that cannot work, naming the option (before any data is read)."""
    from omnire.api import parse_device

    for name in ("max_gaussians", "sky_splats"):
        if getattr(args, name) < 0:
            raise ViewerError(f"--{name.replace('_', '-')} {getattr(args, name)}: expected a count >= 0")
    if not (math.isfinite(args.seconds) and args.seconds >= 0):
        raise ViewerError(f"--seconds {args.seconds}: expected a finite number of seconds >= 0 (0: until Ctrl-C)")
    if not math.isfinite(args.frame):
        raise ViewerError(f"--frame {args.frame}: expected a finite frame number")
    if args.device is not None:
        parse_device(args.device, "--device")


def main(argv: list[str], plugins) -> int:
    from omnire.api import Reconstruction
    from omnire.command_api import output_console
    from omnire_viewer.app import Viewer, check_port
    from omnire_viewer.gate import is_loopback
    from omnire_viewer.scene import ViewerScene

    args = tyro.cli(ViewArgs, args=argv, prog="omnire view")
    check_args(args)
    with nesting_guard(args.run_dir / "run.json"):
        check_run_dir(args.run_dir, args.checkpoint)
    scenario = None
    if args.scenario is not None:
        from omnire_sim import load_scenario

        with nesting_guard(args.scenario):
            scenario = load_scenario(args.scenario)  # format errors before anything is loaded
    check_port(args.host, args.port)
    console = output_console()
    with nesting_guard(args.run_dir / "run.json"):
        recon = Reconstruction.from_run(args.run_dir, plugins, args.checkpoint, device=args.device)
    if not 0 <= args.frame <= recon.scene.num_frames - 1:
        raise ViewerError(f"--frame {args.frame}: outside the scene's frames 0..{recon.scene.num_frames - 1}")
    # the scenario is resolved against the scene here (unknown tracks, times outside the log ...)
    scene = ViewerScene(recon, max_gaussians=args.max_gaussians, sky_count=args.sky_splats, scenario=scenario,
                        plugins=plugins)
    token = args.token if args.token is not None else os.environ.get("OMNIRE_VIEW_TOKEN")
    viewer = Viewer(scene, args.host, args.port, title=f"{recon.run_info.method} - {args.run_dir.name}",
                    frame=args.frame, verbose=False, token=token)
    shown = f", scenario {args.scenario}" if scenario is not None else ""
    banner = (f"omnire view: {viewer.url}  ({recon.run_info.method}, step {recon.step}, "
              f"{recon.num_gaussians():,} Gaussians{shown}; Ctrl-C stops)")
    if not is_loopback(args.host):
        banner += (f"\nomnire view: listening on {args.host}:{viewer.port}, reachable from other machines; "
                   "every client needs the token in the URL above")
    console.print(banner, highlight=False, soft_wrap=True)  # one write: a reader of the URL line gets both
    console.file.flush()
    try:
        start = time.monotonic()
        while not args.seconds or time.monotonic() - start < args.seconds:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        viewer.close()
    return 0
