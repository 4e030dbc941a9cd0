"""Find a libLLVM that Dr.Jit's LLVM backend can use, *before* Dr.Jit is imported.

Dr.Jit loads libLLVM at run time. Debian's libLLVM 15 aborts the whole process inside Mitsuba
(``LLVM ERROR: Cannot select: fminimum``) instead of raising, so we must never let Dr.Jit pick it
up. This module looks for a known-good libLLVM (>= 16), exports ``DRJIT_LIBLLVM_PATH`` to it, and
otherwise raises :class:`LLVMNotFoundError` with the install command.
"""

from __future__ import annotations

import glob
import os
import re

#: Oldest libLLVM major version known to work with Mitsuba 3.9 / Dr.Jit 1.5 on these machines.
MIN_LLVM_MAJOR = 16

#: Directories searched for ``libLLVM*.so*`` (Debian/Ubuntu multiarch, Homebrew, conda).
SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/usr/lib",
    "/usr/local/lib",
    "/usr/lib64",
    "/opt/homebrew/opt/llvm/lib",
    "/usr/local/opt/llvm/lib",
)

INSTALL_HINT = (
    "Install a newer libLLVM, e.g. on Debian/Ubuntu: `apt-get install -y libllvm19`, "
    "or point DRJIT_LIBLLVM_PATH at a libLLVM.so of version >= {min}."
)


class LLVMNotFoundError(RuntimeError):
    """No usable libLLVM for Dr.Jit's LLVM backend was found."""


def _major_version(path: str) -> int | None:
    name = os.path.basename(path)
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)", r"libLLVM\.(\d+)\.dylib"):
        m = re.search(pattern, name)
        if m:
            return int(m.group(1))
    # /usr/lib/llvm-19/lib/libLLVM.so style
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def candidate_libraries(search_dirs: tuple[str, ...] = SEARCH_DIRS) -> list[tuple[int, str]]:
    """All libLLVM shared objects found, as ``(major, path)``, newest first."""
    found: dict[str, int] = {}
    patterns = []
    for d in search_dirs:
        patterns += [os.path.join(d, "libLLVM*.so*"), os.path.join(d, "libLLVM*.dylib")]
    patterns += ["/usr/lib/llvm-*/lib/libLLVM*.so*"]
    for pattern in patterns:
        for path in glob.glob(pattern):
            major = _major_version(path)
            if major is not None and os.path.isfile(path):
                found.setdefault(os.path.realpath(path), major)
    return sorted(((m, p) for p, m in found.items()), reverse=True)


def ensure_llvm(min_major: int = MIN_LLVM_MAJOR) -> str:
    """Make sure Dr.Jit will load a usable libLLVM; return its path.

    Respects an existing ``DRJIT_LIBLLVM_PATH`` (checked for existence and version when the
    version can be read from the file name). Raises :class:`LLVMNotFoundError` otherwise.
    """
    hint = INSTALL_HINT.format(min=min_major)
    preset = os.environ.get("DRJIT_LIBLLVM_PATH")
    if preset:
        if not os.path.isfile(preset):
            raise LLVMNotFoundError(f"DRJIT_LIBLLVM_PATH={preset!r} does not exist. {hint}")
        major = _major_version(preset)
        if major is not None and major < min_major:
            raise LLVMNotFoundError(
                f"DRJIT_LIBLLVM_PATH={preset!r} is libLLVM {major}; versions < {min_major} "
                f"crash Mitsuba's LLVM backend. {hint}")
        return preset
    for major, path in candidate_libraries():
        if major >= min_major:
            os.environ["DRJIT_LIBLLVM_PATH"] = path
            return path
    found = ", ".join(f"{p} (v{m})" for m, p in candidate_libraries()) or "none"
    raise LLVMNotFoundError(
        f"vsrd-mi needs libLLVM >= {min_major} for Dr.Jit's CPU backend; found: {found}. {hint}")
