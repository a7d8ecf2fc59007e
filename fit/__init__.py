"""How parameters are recovered: scene assembly, rendering, the CLI (the fitter comes next)."""
