"""Native extensions: built ahead by ``omnire plugins --build`` (as ``make install`` does) and
reused from the cache by every checkout of the repository."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap

import pytest

from omnire.native import _sources_in
from omnire.plugins import load_plugins


def test_source_copies_are_written_once_and_refreshed_when_they_differ(tmp_path):
    source = tmp_path / "checkout" / "kernel.cpp"
    source.parent.mkdir()
    source.write_text("int f() { return 1; }\n")
    build = tmp_path / "build"
    (copy,) = _sources_in(build, [source])
    assert copy == build / "sources" / "kernel.cpp" and copy.read_text() == source.read_text()
    os.utime(copy, (1_000_000, 1_000_000))  # ninja rebuilds when a source is newer than its object
    assert _sources_in(build, [source]) == [copy] and copy.stat().st_mtime == 1_000_000
    copy.write_text("int f() { return 2; }\n")  # e.g. a copy cut short before the atomic writes
    _sources_in(build, [source])
    assert copy.read_text() == source.read_text()


def _skin_extension():
    from omnire_smpl.skinning import EXTENSION

    module, reason = EXTENSION.load()
    if module is None:
        pytest.skip(f"the SMPL skinning extension does not build here: {reason}")
    return EXTENSION


def test_another_checkout_loads_the_cached_build_without_compiling(tmp_path):
    """The same sources at another path (a fresh clone, a second worktree) reuse the cached
    build: the shared object is not rewritten (a rebuild takes about a minute per extension)."""
    extension = _skin_extension()
    elsewhere = tmp_path / "clone"
    elsewhere.mkdir()
    for source in extension.sources:
        shutil.copy(source, elsewhere / source.name)
    library = next(extension.build_directory().glob("*.so"))
    before = library.stat().st_mtime_ns
    code = textwrap.dedent(f"""
        from pathlib import Path
        from omnire.native import NativeExtension
        from omnire_smpl.skinning import EXTENSION as e
        copy = NativeExtension(e.name, [Path({str(elsewhere)!r}) / s.name for s in e.sources], e.cflags, e.ldflags)
        module, reason = copy.load()
        assert module is not None, reason
        print(copy.build_directory() == e.build_directory(), module.__file__)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    same_directory, loaded = out.stdout.split()
    assert same_directory == "True" and loaded == str(library)
    assert library.stat().st_mtime_ns == before, "the extension was recompiled for a new checkout path"


def test_plugins_build_lists_every_registered_extension():
    registered = load_plugins().native_extensions
    assert {"omnire_raster_cpu", "omnire_lidar_cpu", "omnire_smpl_skin"} <= set(registered.names())
    _skin_extension()
    out = subprocess.run([sys.executable, "-m", "omnire.cli", "plugins", "--build"], capture_output=True, text=True,
                         timeout=900, env=dict(os.environ, COLUMNS="200"))
    assert out.returncode == 0, out.stderr[-2000:]
    table = out.stdout[out.stdout.index("native extensions"):]
    rows = {line.split("│")[1].strip(): line for line in table.splitlines() if line.count("│") >= 4}
    for name in registered.names():
        assert name in rows, table
    assert "available" in rows["omnire_smpl_skin"] and "unavailable" not in rows["omnire_smpl_skin"]
