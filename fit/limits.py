"""Bounds of the numbers commands and configs take (a light module: the CLI reads it at start)."""

#: The largest seed: the renders' seeds are 32-bit (Mitsuba's sampler), and every seed derived
#: from one (a pass's, a view's, a fit step's) is taken modulo 2^32.
MAX_SEED = 2**32 - 1

#: The most samples per pixel a render (`layerfit render`, `synth`, a config's `render.spp`)
#: takes: 2^20 is 16384 passes of `fit.render.image.PASS_SPP`, far past converged (the
#: benchmarks' rendered targets use at most 16384), while a typo's extra digits are refused
#: before any work (Mitsuba's own limit, a 32-bit `sample_count`, was an internal error mid-render).
MAX_SPP = 2**20

#: The quality presets a fit takes (`fit.quality`, `--quality`), from fastest to most accurate;
#: what each does to a schedule: `fit.solvers.schedule.at_quality`.
QUALITIES = ("draft", "default", "best")
