"""The extension must build wherever it can: the other test modules skip when it is
unavailable (no AVX2, no compiler), so a source that stops compiling would otherwise turn
them all into skips instead of failures."""
from __future__ import annotations

import subprocess
import sys

import pytest
from torch.utils import cpp_extension

from omnire_rasterizer_cpu import available
from omnire_rasterizer_cpu._build import EXTENSION, build_directory, build_error_line


def _have_compiler() -> bool:
    import shutil

    return shutil.which(cpp_extension.get_cxx_compiler()) is not None


def test_extension_builds_on_a_machine_that_can_build_it():
    avx2, why = EXTENSION.cpu_supported()
    if not avx2:
        pytest.skip(why)
    if not _have_compiler():
        pytest.skip(f"no C++ compiler ({cpp_extension.get_cxx_compiler()}) on PATH")
    ok, reason = available("cpu")
    assert ok, f"the cpu rasterizer did not build on a machine with AVX2 and a compiler: {reason}"


def test_build_error_names_the_compiler_error_not_ninjas_last_line():
    out = ("Error building extension 'x':\n[1/2] c++ -c raster.cpp\n"
           "raster.cpp:283:16: error: 'narrow_rect' was not declared in this scope\n"
           "raster.cpp:290:1: error: second\nninja: build stopped: subcommand failed.\n")
    assert build_error_line(out) == "raster.cpp:283:16: error: 'narrow_rect' was not declared in this scope"
    assert build_error_line("ninja: build stopped: subcommand failed.") == "ninja: build stopped: subcommand failed."


def test_a_lock_left_by_a_killed_build_does_not_stall_later_loads():
    """torch's build lock is a file: a process killed while it built or loaded the extension
    leaves it behind, and torch's loader would then wait on it forever (as a CI run once did,
    until its time ran out). A new process must notice and load anyway."""
    ok, reason = available("cpu")
    if not ok:
        pytest.skip(reason)
    stale = build_directory() / "lock"
    stale.touch()
    try:
        proc = subprocess.run(
            [sys.executable, "-c", "from omnire_rasterizer_cpu._build import extension; extension(); print('loaded')"],
            capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        pytest.fail(f"loading the extension waited on the stale {stale} for 10 minutes")
    finally:
        stale.unlink(missing_ok=True)
    assert proc.returncode == 0 and "loaded" in proc.stdout, proc.stderr[-2000:]
    assert "left by an extension build that was killed" in proc.stderr
