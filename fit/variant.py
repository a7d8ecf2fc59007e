"""Choose the Mitsuba variant once, after making sure its JIT backend can run.

Dr.Jit's LLVM backend loads a shared libLLVM at run time. libLLVM 14 and 15 (Debian 12's defaults)
abort the process at the first render (``LLVM ERROR: Cannot select ... fminimum``), so before any
``llvm_*`` variant is set we look for libLLVM >= 16 ourselves, point ``DRJIT_LIBLLVM_PATH`` at
it and fail with one line that says what to install when there is none.
"""

from __future__ import annotations

import glob
import logging
import os
import re
import subprocess

log = logging.getLogger(__name__)

DEFAULT_VARIANT = "llvm_ad_rgb"
MIN_LLVM = 16
_SEARCH_DIRS = (
    "/usr/lib/x86_64-linux-gnu",
    "/usr/lib/aarch64-linux-gnu",
    "/lib/x86_64-linux-gnu",
    "/lib/aarch64-linux-gnu",
    "/usr/lib",
    "/usr/lib64",
    "/usr/local/lib",
    "/usr/lib/llvm-*/lib",
    "/opt/homebrew/opt/llvm/lib",
)
# libLLVM-19.so, libLLVM-19.so.1, libLLVM.so.19.1, libLLVM.so.19
_VERSION = re.compile(r"libLLVM(?:-(\d+)(?:\.\d+)*\.so|\.so\.(\d+))")


#: The variants layerfit runs: its plugins are RGB and its fits differentiate the renders.
SUPPORTED = ("llvm_ad_rgb", "cuda_ad_rgb")


class BackendError(RuntimeError):
    """The requested Mitsuba variant cannot run on this machine; the message says what to do."""


class VariantError(BackendError):
    """The variant asked for is not one layerfit runs, or needs a device this machine lacks
    (bad input: the CLI exits 2)."""


def llvm_version(path: str) -> int | None:
    """Major version of a libLLVM shared library, read from its file name (None if unknown)."""
    match = _VERSION.search(os.path.basename(path))
    if match is None:
        return None
    return int(match.group(1) or match.group(2))


def _candidates() -> list[str]:
    found = []
    for pattern in _SEARCH_DIRS:
        for folder in glob.glob(pattern):
            found += glob.glob(os.path.join(folder, "libLLVM*.so*"))
    try:
        out = subprocess.run(
            ["ldconfig", "-p"], capture_output=True, text=True, timeout=10, check=False
        ).stdout
        found += [line.split("=>")[-1].strip() for line in out.splitlines() if "libLLVM" in line]
    except (OSError, subprocess.SubprocessError):
        pass
    return found


def find_libllvm() -> str | None:
    """Path of the newest libLLVM >= 16 on this machine, or None."""
    usable = [(llvm_version(p), p) for p in set(_candidates()) if os.path.exists(p)]
    usable = [(v, p) for v, p in usable if v is not None and v >= MIN_LLVM]
    return max(usable)[1] if usable else None


def ensure_llvm() -> str:
    """Make sure Dr.Jit's LLVM backend will load a libLLVM >= 16 and return its path.

    Honours an explicit ``DRJIT_LIBLLVM_PATH`` when it names a usable version.
    """
    explicit = os.environ.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        version = llvm_version(explicit)
        if not os.path.exists(explicit):
            raise BackendError(f"DRJIT_LIBLLVM_PATH={explicit} does not exist; unset it or fix it.")
        if version is not None and version < MIN_LLVM:
            raise BackendError(
                f"DRJIT_LIBLLVM_PATH={explicit} is libLLVM {version}, which crashes Dr.Jit; "
                f"install libLLVM >= {MIN_LLVM} (Debian/Ubuntu: apt-get install libllvm19)."
            )
        return explicit
    path = find_libllvm()
    if path is None:
        raise BackendError(
            f"No libLLVM >= {MIN_LLVM} found (Dr.Jit's CPU backend needs it): on Debian/Ubuntu run "
            "`sudo apt-get install libllvm19`, or set DRJIT_LIBLLVM_PATH to a libLLVM >= 16."
        )
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    return path


def select_variant(variant: str | None = None) -> str:
    """Set the Mitsuba variant (argument, else ``LAYERFIT_VARIANT``, else ``llvm_ad_rgb``)."""
    variant = variant or os.environ.get("LAYERFIT_VARIANT") or DEFAULT_VARIANT
    if variant not in SUPPORTED:
        raise VariantError(
            f"--variant / LAYERFIT_VARIANT {variant!r}: not a variant layerfit runs; choose "
            f"{' (CPU) or '.join(SUPPORTED)} (GPU)"
        )
    if variant.startswith("llvm"):
        path = ensure_llvm()
        log.debug("Dr.Jit uses %s", path)
    import drjit as dr
    import mitsuba as mi

    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        raise VariantError(
            f"--variant / LAYERFIT_VARIANT {variant!r}: no usable CUDA device or driver on this "
            f"machine; use {DEFAULT_VARIANT} (CPU)"
        )
    if variant not in mi.variants():
        raise BackendError(
            f"Mitsuba variant {variant!r} is not built into this Mitsuba; "
            f"choose one of {', '.join(v for v in SUPPORTED if v in mi.variants())}."
        )
    mi.set_variant(variant)
    return variant
