"""The public module of the core for command and benchmark authors, beside :mod:`omnire.api`.

A plugin's ``omnire <name>`` command (``CommandSpec.main(argv, plugins)``) imports what it
prints, writes and measures with from here: the console the core's commands print with,
the MP4 writer, this process's memory, the camera paths of ``omnire render`` and ``omnire sim``, and the pieces of
``omnire bench train`` that other comparisons reuse (its arguments, table, plot and
``--methods`` entry parser), and the parser of ``omnire train``'s command line (for a
benchmark that builds its trainers in process and takes method flags as ``omnire train``
does). Everything else it needs (specs, the scene runtime, errors, atomic writes) is in
:mod:`omnire.api`. docs/plugins.md lists both public modules.
"""
from omnire.bench.memory import process_status_kib
from omnire.bench.train import TrainBenchArgs, markdown_table, parse_entry
from omnire.bench.train import plot as plot_train_bench
from omnire.camerapath import CameraPath, file_path, interpolated_path, recorded_path, rig_poses
from omnire.io.video import Mp4Writer, VideoWriteError, write_mp4
from omnire.runconfig import parse_train_args
from omnire.ui import output_console

__all__ = [
    "CameraPath", "Mp4Writer", "TrainBenchArgs", "VideoWriteError", "file_path", "interpolated_path", "markdown_table",
    "output_console", "parse_entry", "parse_train_args", "plot_train_bench", "process_status_kib", "recorded_path",
    "rig_poses", "write_mp4",
]
