"""The extension must build wherever it can: the other test modules skip when it is
unavailable (no AVX2, no compiler), so a source that stops compiling would otherwise turn
them all into skips instead of failures."""
from __future__ import annotations

import pytest
from torch.utils import cpp_extension

from omnire_rasterizer_cpu import available
from omnire_rasterizer_cpu._build import _cpu_supports_avx2, build_error_line


def _have_compiler() -> bool:
    import shutil

    return shutil.which(cpp_extension.get_cxx_compiler()) is not None


def test_extension_builds_on_a_machine_that_can_build_it():
    avx2, why = _cpu_supports_avx2()
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
