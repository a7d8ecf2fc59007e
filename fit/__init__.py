"""How parameters are recovered, by responsibility (data flows down this list):

- `fit.config`: typed render and fit configs (TOML).
- `fit.material`: a material as data: the Mitsuba dict and its parameter table, the key grammar,
  free parameters, the native preset.
- `fit.render`: Mitsuba scenes, forward renders, the `Renderer` and the one JAX <-> Dr.Jit bridge.
- `fit.solvers`: the problem and its residuals, one solver per module and their registry,
  schedules, uncertainty.
- `fit.output`: figures and the HTML report of a run, through one atomic writer.
- `fit.commands`: one module per command (a function each); `fit.cli` parses options and calls
  them, `fit.console` shows their progress and results.
- `fit.bench`: one module per benchmark, `fit.bench.run` the `bench` command.
- `fit.batch`, `fit.cluster`: batches of fits as Ray tasks, and joining or starting Ray.
- `fit.variant`: choose the Mitsuba variant once (before anything imports Mitsuba).

JAX runs on the CPU unless ``JAX_PLATFORMS`` says otherwise: its work here is the solvers' small
vectors and images that cross from Dr.Jit through NumPy anyway, and on a GPU it would otherwise take
75 % of the device's memory at its first array, which Dr.Jit's renders need (measured on an H200:
parallel test workers ran out of GPU memory).

JAX keeps its compiled solvers in ``$XDG_CACHE_HOME/layerfit/jax`` (``~/.cache``; at most 256 MiB,
least recently used dropped) unless ``JAX_COMPILATION_CACHE_DIR`` says otherwise (empty: none), as
Dr.Jit keeps its kernels in ``~/.drjit``: each command compiled them again, 1.8 s a command on
the Cycles sphere (2-core VM, 2026-12-05).
"""

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")


def _jax_cache() -> None:
    """Point JAX's persistent compilation cache at layerfit's cache folder (see above)."""
    base = os.environ.get("XDG_CACHE_HOME") or (
        os.path.join(os.environ["HOME"], ".cache") if os.environ.get("HOME") else None
    )
    if base is None or "JAX_COMPILATION_CACHE_DIR" in os.environ:
        return
    os.environ["JAX_COMPILATION_CACHE_DIR"] = os.path.join(base, "layerfit", "jax")
    # every compile is cached (JAX's default keeps only those over a second: none of ours)
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")
    os.environ.setdefault("JAX_COMPILATION_CACHE_MAX_SIZE", str(256 * 2**20))


_jax_cache()


def _drop_shadowing_paths() -> None:
    """Drop `sys.path` entries (other than this project's root) holding a folder named like one
    of its packages: Ray starts its workers with the driver's working folder on `sys.path`, and
    a user's photo folder `captures/` there, a namespace package to Python, hid this project's
    `captures` from an editable install (every batch fit failed on an ImportError)."""
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent
    names = ("captures", "materials")
    keep = []
    for entry in sys.path:
        folder = Path(entry or os.getcwd())
        try:
            shadows = folder.resolve() != root and any((folder / n).is_dir() for n in names)
        except OSError:
            shadows = False
        if not shadows:
            keep.append(entry)
    sys.path[:] = keep


_drop_shadowing_paths()
