"""Build (first use) and load a plugin's C++ extension.

Plugins with native kernels (the cpu rasterizer, SMPL skinning) describe their extension
with a :class:`NativeExtension`; it is compiled with ``torch.utils.cpp_extension.load`` into
a cache directory keyed by the sources' hash, the compiler flags and the torch installation
(version and path), from copies of the sources kept there (so the build does not depend on
where the repository is checked out). A rebuild happens only when one of them changes, and
later processes load the cached ``.so`` in milliseconds. Any failure (no compiler, a CPU
without a required instruction set, ...) is recorded once and reported by
:meth:`NativeExtension.load` as ``(None, reason)``, so callers can fall back to torch.

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
import threading
from pathlib import Path
from types import ModuleType
from typing import Optional, Sequence

from omnire.io.atomic import atomic_write_bytes
from omnire.io.cache import user_cache_dir

log = logging.getLogger(__name__)


def cache_dir() -> Path:
    """Root of the extension cache (see the module docstring)."""
    return user_cache_dir("extensions", "OMNIRE_EXTENSIONS_DIR")


def cpu_lacks(flags: Sequence[str]) -> list[str]:
    """The CPU feature flags of ``flags`` (``/proc/cpuinfo`` names, e.g. ``avx2``) this CPU
    lacks; empty when it has them all or cannot tell (no ``/proc/cpuinfo``: the build or the
    first call decides)."""
    try:
        text = Path("/proc/cpuinfo").read_text()
    except OSError:
        return []
    for line in text.splitlines():
        if line.startswith("flags"):
            have = set(line.split(":", 1)[1].split())
            return [f for f in flags if f not in have]
    return []


def build_error_line(message: str) -> str:
    """The line of a failed build's output that says what failed: the compiler's first
    ``error:`` line when there is one (ninja's own last line only says that it stopped)."""
    lines = [ln.strip() for ln in message.strip().splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    return (errors or lines or [""])[0 if errors else -1][:300]


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


def _sources_in(build_dir: Path, sources: Sequence[Path]) -> list[Path]:
    """Copies of ``sources`` in ``build_dir/sources``, compiled instead of the originals: the
    build rules then name the same files whichever checkout of the repository an environment
    runs (ninja rebuilds when a rule's source path changes, so a checkout moved or cloned
    again would otherwise recompile for minutes what the cache already holds). A copy is rewritten only when its
    bytes differ (the build directory is keyed by the sources' hash, so only after a killed
    copy): ninja also rebuilds when a source is newer than its object."""
    copies = []
    for source in sources:
        copy = build_dir / "sources" / source.name
        data = source.read_bytes()
        if not copy.is_file() or copy.read_bytes() != data:
            atomic_write_bytes(copy, data)
        copies.append(copy)
    return copies


class NativeExtension:
    """One C++ extension: ``name`` (the cache directory's and module's prefix), its
    ``sources``, compiler and linker flags, and the CPU flags it is compiled for (a CPU
    without them reports the extension unavailable instead of crashing on an illegal
    instruction). Builds at most once per process; :meth:`load` is thread-safe."""

    def __init__(self, name: str, sources: Sequence[Path], cflags: Sequence[str], ldflags: Sequence[str] = (),
                 cpu_flags: Sequence[str] = (), purpose: str = "") -> None:
        self.name = name
        self.sources = [Path(s) for s in sources]
        # tuples, handed to torch as fresh lists: torch appends its own libraries to the lists it gets
        self.cflags, self.ldflags, self.cpu_flags = tuple(cflags), tuple(ldflags), tuple(cpu_flags)
        self.purpose = purpose or name
        self._lock = threading.Lock()
        self.state: dict[str, object] = {}  # "module" or "error" once tried

    def cpu_supported(self) -> tuple[bool, str]:
        """``(False, reason)`` when this CPU lacks a flag the extension is compiled for."""
        missing = cpu_lacks(self.cpu_flags)
        if missing:
            return False, (f"CPU lacks {', '.join(missing)} (the kernel is compiled with "
                           f"{' '.join('-m' + f for f in self.cpu_flags)})")
        return True, ""

    def build_directory(self) -> Path:
        """Where these sources, flags and this torch installation build to:
        ``cache_dir()/<name>_<hash>``."""
        import torch

        digest = hashlib.sha256()
        for source in self.sources:
            digest.update(source.read_bytes())
        digest.update(" ".join(self.cflags + self.ldflags).encode())
        # the torch installation, not only its version: the build rules name its headers by
        # path, so two environments sharing one directory would rebuild it in turn
        digest.update(f"{torch.__version__} {Path(torch.__file__).parent}".encode())
        return cache_dir() / f"{self.name}_{digest.hexdigest()[:12]}"

    def _build(self) -> ModuleType:
        from torch.utils import cpp_extension

        build_dir = self.build_directory()
        build_dir.mkdir(parents=True, exist_ok=True)
        with _builders_take_turns(build_dir):
            return cpp_extension.load(
                name=build_dir.name,
                sources=[str(source) for source in _sources_in(build_dir, self.sources)],
                extra_cflags=list(self.cflags),
                extra_ldflags=list(self.ldflags),
                build_directory=str(build_dir),
                verbose=False,
            )

    def load(self) -> tuple[Optional[ModuleType], str]:
        """``(module, "")`` or ``(None, reason)``; builds at most once per process."""
        with self._lock:
            if "module" in self.state:
                return self.state["module"], ""  # type: ignore[return-value]
            if "error" in self.state:
                return None, str(self.state["error"])
            ok, reason = self.cpu_supported()
            if not ok:
                self.state["error"] = reason
            else:
                try:
                    self.state["module"] = self._build()
                    return self.state["module"], ""  # type: ignore[return-value]
                except Exception as exc:  # noqa: BLE001 - any build failure means "unavailable"
                    self.state["error"] = (f"C++ extension failed to build: {type(exc).__name__}: "
                                           f"{build_error_line(str(exc))}")
            log.warning("%s unavailable: %s", self.purpose, self.state["error"])
            return None, str(self.state["error"])

    def module(self) -> ModuleType:
        """The loaded extension; a RuntimeError saying why when it is unavailable."""
        mod, reason = self.load()
        if mod is None:
            raise RuntimeError(f"the {self.purpose}'s native extension is unavailable: {reason}")
        return mod
