"""Build (first use) and load the C++ extension.

The extension is compiled with ``torch.utils.cpp_extension.load`` into a cache directory
keyed by the source hash, compiler flags and torch version, so a rebuild happens only when
one of them changes; later processes load the cached ``.so`` in milliseconds. Building takes
about a minute on 2 cores. Any failure (no compiler, no AVX2 on this CPU, ...) is recorded
once and reported by :func:`load_extension` as ``(None, reason)``.

Builders take turns through an ``flock`` on the build directory, which the kernel drops
when its holder dies. torch's own lock is a plain file (``<build dir>/lock``) that a build
killed midway leaves behind, and every later load would wait on it forever; whoever holds
the ``flock`` knows that no one else is building, so such a file is stale and is removed.

Environment: ``OMNIRE_EXTENSIONS_DIR`` overrides the cache root
(default ``$XDG_CACHE_HOME/omnire/extensions`` or ``~/.cache/omnire/extensions``).
"""
from __future__ import annotations

import contextlib
import hashlib
import logging
import os
import threading
from pathlib import Path
from types import ModuleType
from typing import Optional

log = logging.getLogger(__name__)

SOURCES = [Path(__file__).parent / "csrc" / name for name in ("raster.cpp", "ssim.cpp")]
# Portable flags: AVX2 + FMA (not -march=native, which ties the .so to one machine).
# -ffp-contract=off keeps forward and backward bit-identical in their skip/stop decisions.
# Tuples, passed to torch as fresh lists: torch appends its own libraries to the lists it gets.
CFLAGS = ("-O3", "-mavx2", "-mfma", "-fopenmp", "-ffp-contract=off", "-std=c++17")
LDFLAGS = ("-fopenmp",)

_lock = threading.Lock()
_state: dict[str, object] = {}


def _cpu_supports_avx2() -> tuple[bool, str]:
    try:
        flags = Path("/proc/cpuinfo").read_text()
    except OSError:
        return True, ""  # cannot tell (non-Linux): let the build / first call decide
    for line in flags.splitlines():
        if line.startswith("flags"):
            have = set(line.split(":", 1)[1].split())
            missing = [f for f in ("avx2", "fma") if f not in have]
            if missing:
                return False, f"CPU lacks {', '.join(missing)} (the kernel is compiled with -mavx2 -mfma)"
            return True, ""
    return True, ""


def cache_dir() -> Path:
    root = os.environ.get("OMNIRE_EXTENSIONS_DIR")
    if root:
        return Path(root)
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "omnire" / "extensions"


@contextlib.contextmanager
def _builders_take_turns(build_dir: Path):
    """Hold an exclusive ``flock`` on ``build_dir/build.lock``, then clear a stale torch lock."""
    try:
        import fcntl
    except ImportError:  # not POSIX: torch's own lock only
        yield
        return
    with open(build_dir / "build.lock", "a") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX)
        except OSError as exc:  # a filesystem without locks (some network mounts)
            log.warning("no lock on %s (%s): relying on torch's lock file alone", handle.name, exc)
            yield
            return
        try:
            stale = build_dir / "lock"
            if stale.exists():
                log.warning("removing %s, left by an extension build that was killed", stale)
                stale.unlink(missing_ok=True)
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


def build_directory() -> Path:
    """Where this source, these flags and this torch build to: ``cache_dir()/<name>``."""
    import torch

    digest = hashlib.sha256()
    for source in SOURCES:
        digest.update(source.read_bytes())
    digest.update(" ".join(CFLAGS + LDFLAGS).encode())
    digest.update(torch.__version__.encode())
    return cache_dir() / ("omnire_raster_cpu_" + digest.hexdigest()[:12])


def _build() -> ModuleType:
    from torch.utils import cpp_extension

    build_dir = build_directory()
    name = build_dir.name
    build_dir.mkdir(parents=True, exist_ok=True)
    with _builders_take_turns(build_dir):
        return cpp_extension.load(
            name=name,
            sources=[str(source) for source in SOURCES],
            extra_cflags=list(CFLAGS),
            extra_ldflags=list(LDFLAGS),
            build_directory=str(build_dir),
            verbose=False,
        )


def build_error_line(message: str) -> str:
    """The line of a failed build's output that says what failed: the compiler's first
    ``error:`` line when there is one (ninja's own last line only says that it stopped)."""
    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    return (errors or lines or [""])[0 if errors else -1][:300]


def load_extension() -> tuple[Optional[ModuleType], str]:
    """Return ``(module, "")`` or ``(None, reason)``; builds at most once per process."""
    with _lock:
        if "module" in _state:
            return _state["module"], ""  # type: ignore[return-value]
        if "error" in _state:
            return None, str(_state["error"])
        ok, reason = _cpu_supports_avx2()
        if not ok:
            _state["error"] = reason
        else:
            try:
                _state["module"] = _build()
                return _state["module"], ""  # type: ignore[return-value]
            except Exception as exc:  # noqa: BLE001 - any build failure means "unavailable"
                _state["error"] = f"C++ extension failed to build: {type(exc).__name__}: {build_error_line(str(exc))}"
        log.warning("omnire cpu rasterizer unavailable: %s", _state["error"])
        return None, str(_state["error"])


def extension() -> ModuleType:
    """The loaded extension; a RuntimeError saying why when it is unavailable."""
    mod, reason = load_extension()
    if mod is None:
        raise RuntimeError(f"the cpu rasterizer's native extension is unavailable: {reason}")
    return mod
