"""The one JAX <-> Dr.Jit bridge: `render(x, seed)` as a JAX function of physical parameter values.

Dr.Jit 1.5 cannot wrap JAX -> Dr.Jit, so the bridge is `jax.pure_callback` into `Renderer`, with two
derivative modes (see ../shared/FACTS.md for what each supports):

- `"reverse"` (`jax.custom_vjp`): the backward pass is one `render_backward` per view; for many
  parameters (textures) and for gradient-based minimisers (Adam, BFGS). Its `paired(x, seed,
  cotangent)` returns the image and a VJP from the same paths, in one pass.
- `"jacobian"` (`jax.custom_jvp`): the callback returns the image and its full Jacobian (one
  `render_forward` per parameter component) and the tangent is `J @ t` in JAX, so every transform
  works (jvp, jacfwd, grad, linearize); for least squares on few parameters (Levenberg-Marquardt).

Values cross the boundary as float32; the seed is an int32 scalar under the caller's control; the
sample counts are fixed per bridge (they are not traced: no recompiling when a phase changes them).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .renderer import Renderer

MODES = ("reverse", "jacobian")


def make_render(
    renderer: Renderer,
    mode: str = "reverse",
    spp: int = 16,
    jacobian_spp: int | None = None,
    grad_spp: int | None = None,
):
    """`render(x: f32[P], seed: i32[]) -> f32[N]` at `spp`, differentiable in `x` by `mode`
    (`jacobian_spp`: see `Renderer.jacobian`; `grad_spp`: the reverse pass's samples per pixel,
    `spp` unless given)."""
    if mode not in MODES:
        raise ValueError(f"mode {mode!r}; choose one of {', '.join(MODES)}")
    out = jax.ShapeDtypeStruct((renderer.size,), jnp.float32)
    grad = jax.ShapeDtypeStruct((renderer.n_params,), jnp.float32)
    jac = jax.ShapeDtypeStruct((renderer.size, renderer.n_params), jnp.float32)

    def _render(x, seed):
        return renderer.render(np.asarray(x, np.float32), int(seed), spp)

    def _vjp(x, seed, cotangent):
        return renderer.vjp(
            np.asarray(x, np.float32),
            int(seed),
            grad_spp or spp,
            np.asarray(cotangent, np.float32),
        )

    def _jacobian(x, seed):
        return renderer.jacobian(np.asarray(x, np.float32), int(seed), spp, jacobian_spp)

    def _render_vjp(x, seed, cotangent):
        x, cotangent = (np.asarray(a, np.float32) for a in (x, cotangent))
        return renderer.render_vjp(x, int(seed), spp, cotangent)

    def paired(x, seed, cotangent):
        """`(render(x, seed), J^T cotangent)` from the same paths: one reverse pass whose primal
        pass is the image (`Renderer.render_vjp`); not differentiable."""
        args = (x.astype(jnp.float32), seed, cotangent.astype(jnp.float32))
        return jax.pure_callback(_render_vjp, (out, grad), *args, vmap_method="sequential")

    def call(x, seed):
        return jax.pure_callback(_render, out, x, seed, vmap_method="sequential")

    if mode == "reverse":

        @jax.custom_vjp
        def render(x, seed):
            return call(x.astype(jnp.float32), seed)

        def fwd(x, seed):
            return render(x, seed), (x, seed)

        def bwd(residuals, cotangent):
            x, seed = residuals
            g = jax.pure_callback(
                _vjp,
                grad,
                x.astype(jnp.float32),
                seed,
                cotangent.astype(jnp.float32),
                vmap_method="sequential",
            )
            return g.astype(x.dtype), None

        render.defvjp(fwd, bwd)
        if grad_spp in (None, spp):
            render.paired = paired
        return render

    @jax.custom_jvp
    def render(x, seed):
        return call(x.astype(jnp.float32), seed)

    @render.defjvp
    def render_jvp(primals, tangents):
        x, seed = primals
        tx, _ = tangents
        image, jacobian = jax.pure_callback(
            _jacobian, (out, jac), x.astype(jnp.float32), seed, vmap_method="sequential"
        )
        return image, jacobian @ tx.astype(jnp.float32)

    return render
