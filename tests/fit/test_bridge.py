"""The bridge from JAX to Mitsuba: parameters, derivatives, threads, kernels, frozen renders."""

from __future__ import annotations

import drjit as dr
import jax
import jax.numpy as jnp
import mitsuba as mi
import numpy as np
import pytest
from sphere_problems import KEYS, TRUTH, two_views

from fit.material import resolve, to_physical, to_unconstrained
from fit.render import GRAD_SEED_OFFSET, MATERIAL_PREFIX, Renderer, make_render


def truth_vector():
    return np.array(
        [*TRUTH["glaze.pigment"], TRUTH["glaze.roughness"], TRUTH["glaze.ior"]], np.float32
    )


def test_free_parameters_resolve_and_round_trip(problem):
    free = problem.free
    assert [f.traverse for f in free] == ["pigment.value", "roughness", "ior"]
    u = to_unconstrained(free, TRUTH)
    np.testing.assert_allclose(to_physical(free, u), truth_vector(), rtol=1e-6)
    with pytest.raises(KeyError, match=r"not a built parameter; choose from glaze\.pigment"):
        resolve(problem.material, ["glaze.shininess"])
    with pytest.raises(KeyError, match="no layer 'clay' is built"):
        resolve(problem.material, ["clay.sigma"])


def test_reverse_and_forward_derivatives_agree(problem):
    """The VJP (one `render_backward`) equals J^T c with J from one `render_forward` per
    parameter, when both use the same random numbers."""
    renderer = problem.renderer()
    x = truth_vector()
    c = np.random.default_rng(0).normal(size=renderer.size).astype(np.float32)
    vjp = renderer.vjp(x, 5, 16, c)
    _, jac = renderer.jacobian(x, 5 + GRAD_SEED_OFFSET, 16)
    np.testing.assert_allclose(vjp, jac.T @ c, rtol=1e-3, atol=1e-3 * np.abs(vjp).max())


def flipped(a: np.ndarray, b: np.ndarray) -> float:
    """The fraction of entries where `a` and `b` differ by more than float32 rounding: a frozen
    replay's kernels are compiled with other literals than a plain call's, and now and then a
    branch's rounding sends a sample down another path (whole pixels, a sample's worth each;
    wrong replays were 15-35 % off everywhere)."""
    return float(np.mean(~np.isclose(a, b, rtol=1e-3, atol=1e-5)))


def test_a_jacobians_columns_share_one_primal_pass(problem, monkeypatch):
    """`jacobian`'s one primal pass for all columns gives the image `render` gives and the
    columns Mitsuba's `render_forward` gives one by one at the same seed: exactly unfrozen; its
    frozen replays beside other scenes with a few samples flipped (measured: up to 27 of 51840
    entries of the Jacobian, whole pixels, 0.2 % of its largest entry)."""
    cfg, capture = two_views()
    free = resolve(cfg.material, KEYS)
    x = truth_vector()
    for freeze in (False, True):
        renderer = Renderer(capture, cfg.material, free, freeze=freeze)
        assert renderer.imaged
        # two recordings (Dr.Jit's auto-opaque literals), then replays
        runs = [renderer.jacobian(x * np.float32(1 + 0.05 * k), 3 + k, 4) for k in range(4)]
        with monkeypatch.context() as m:
            m.setattr(Renderer, "imaged", property(lambda self: False))  # per column
            columns = [renderer.jacobian(x * np.float32(1 + 0.05 * k), 3 + k, 4) for k in range(4)]
        for (image, jac), (image_1, jac_1) in zip(runs, columns, strict=True):
            assert np.all(np.any(jac != 0, axis=0))
            if freeze:
                assert flipped(image, image_1) < 0.005
                assert flipped(jac, jac_1) < 0.005
            else:
                np.testing.assert_array_equal(image, image_1)
                np.testing.assert_array_equal(jac, jac_1)
        assert not freeze or renderer.groups[0].jacobian_column.frozen is not None


def test_a_reverse_pass_renders_its_own_image(problem):
    """`render_vjp`'s one pass gives the image `render` gives at its seed and the gradient `vjp`
    gives at the same seed, replay after replay of its frozen pass, as values and seeds change.
    The gradients agree within their float32 sums' order (a frozen replay of `vjp` itself moved
    a component by 0.3 % of the largest against its unfrozen pass at the same seed), far within
    their Monte Carlo noise from one seed to the next (here their largest component 42-247)."""
    renderer = problem.renderer()
    assert renderer.imaged
    rng = np.random.default_rng(1)
    c = rng.normal(size=renderer.size).astype(np.float32)
    for k, seed in enumerate((3, 4, 5, 6)):
        x = truth_vector() * np.float32(1 + 0.1 * k)
        image, grad = renderer.render_vjp(x, seed, 8, c)
        np.testing.assert_allclose(image, renderer.render(x, seed, 8), rtol=1e-5, atol=1e-6)
        own = renderer.vjp(x, seed - GRAD_SEED_OFFSET, 8, c)
        np.testing.assert_allclose(grad, own, rtol=0, atol=5e-3 * np.abs(own).max())
    assert renderer.groups[0].reverse_imaged.frozen is not None


@pytest.mark.parametrize(
    "integrator, expected",
    [("prb", True), ("prb_basic", True), ("prb_projective", False), ("direct_projective", False)],
)
def test_only_path_replay_integrators_render_their_reverse_pass_image(integrator, expected):
    """A projective integrator's reverse pass adds boundary terms that `_backward_with_image`
    does not: `render_vjp` renders its image apart there."""
    from fit.render.renderer import imaged

    assert imaged(mi.load_dict({"type": integrator})) is expected


def test_bridge_gradient_equals_mitsubas_own(problem):
    """JAX's grad through the bridge (both modes) equals `dr.backward` through `mi.render`, within
    Monte Carlo noise at 256 spp (each decorrelates its gradient pass differently). Roughness
    barely moves the mean image: its component is at noise level, hence the atol."""
    renderer = problem.renderer()
    x = truth_vector()
    grads = []
    for mode in ("reverse", "jacobian"):
        f = make_render(renderer, mode, 256)
        grads.append(
            np.asarray(jax.grad(lambda x, s, f=f: jnp.mean(f(x, s)))(jnp.asarray(x), jnp.int32(5)))
        )
    scene, params = renderer.scenes[0], renderer.params[0]
    renderer._set(0, x, grad=True)
    image = mi.render(scene, params, spp=256, seed=5)
    dr.backward(dr.mean(image[..., :3]))
    own = np.concatenate(
        [np.ravel(dr.grad(params[MATERIAL_PREFIX + f.traverse])) for f in problem.free]
    )
    renderer._set(0, x)  # drop the AD state
    for grad in grads:
        np.testing.assert_allclose(grad, own, rtol=0.1, atol=0.1 * np.abs(own).max())


def test_a_renderer_never_renders_on_two_threads_at_once(problem, monkeypatch):
    """The bridge's callbacks run on XLA's threads, and ones that do not depend on each other
    may run at once (in the cup's main job a reverse pass entered while an image rendered on
    another thread, 2026-12-02). A `Renderer` sets its scenes' values before each pass, and
    Dr.Jit aborted when used from two threads at once, so its passes run one at a time: here
    from two threads, each pass held long enough for the other to start if it could."""
    import threading
    import time

    renderer = problem.renderer()
    group = renderer.groups[0]
    state = {"inside": 0, "most": 0}
    lock = threading.Lock()

    def held(fn):
        def wrapper(*args):
            with lock:
                state["inside"] += 1
                state["most"] = max(state["most"], state["inside"])
            time.sleep(0.05)
            try:
                return fn(*args)
            finally:
                with lock:
                    state["inside"] -= 1

        return wrapper

    monkeypatch.setattr(group, "primal", held(group.primal))
    monkeypatch.setattr(group, "reverse", held(group.reverse))
    x, ones = truth_vector(), np.ones(renderer.size, np.float32)
    errors = []

    def work(k):
        try:
            for i in range(3):
                renderer.render(x, 10 * k + i, 4)
                renderer.vjp(x, 10 * k + i, 4, ones)
        except Exception as err:  # reported below
            errors.append(err)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and state["most"] == 1, (errors, state)


@pytest.mark.parametrize("component, h, rtol", [(1, 0.01, 0.03), (4, 0.01, 0.1)])
def test_jvp_matches_finite_differences(problem, component, h, rtol):
    """Forward-mode tangents equal central differences of renders with a shared seed (pigment
    green: linear; ior: smooth, but it also moves the lobe choice, so FD is noisier: 8 %)."""
    renderer = problem.renderer()
    f = make_render(renderer, "jacobian", 64)
    x = jnp.asarray(truth_vector())
    t = jnp.zeros(5, jnp.float32).at[component].set(1.0)
    _, jvp = jax.jvp(lambda x: f(x, jnp.int32(3)), (x,), (t,))
    fd = (f(x + h * t, jnp.int32(3)) - f(x - h * t, jnp.int32(3))) / (2 * h)
    assert float(jnp.sum(jvp)) == pytest.approx(float(jnp.sum(fd)), rel=rtol)


def test_render_does_not_recompile(problem):
    """Scalars are opaque: new parameter values and sample counts reuse the compiled kernels
    (unfrozen: frozen functions replay without compiling anyway). A kernel compiled anew (one
    with a value baked in) is a JIT kernel of the history with `cache_hit` 0."""
    renderer = Renderer(problem.capture, problem.material, problem.free, freeze=False)
    x = truth_vector()
    renderer.render(x, 0, 4)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()  # reading it clears it
        renderer.render(x * np.float32(1.01), 1, 8)
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    assert jit, "the render launched no kernel"
    assert all(k["cache_hit"] for k in jit), [k["hash"] for k in jit if not k["cache_hit"]]


def test_frozen_renders_equal_unfrozen():
    """Frozen functions (one per view) replay what plain calls compute, across views with
    different cameras, seeds, sample counts and parameter values: primal renders, reverse passes
    and the forward passes of a Jacobian."""
    cfg, capture = two_views()
    free = resolve(cfg.material, KEYS)
    frozen = Renderer(capture, cfg.material, free)
    plain = Renderer(capture, cfg.material, free, freeze=False)
    c = np.random.default_rng(1).normal(size=frozen.size).astype(np.float32)
    for seed, spp, scale in [(1, 4, 1.0), (2, 4, 1.1), (3, 8, 0.9)]:
        x = truth_vector() * np.float32(scale)
        np.testing.assert_array_equal(frozen.render(x, seed, spp), plain.render(x, seed, spp))
        np.testing.assert_allclose(
            frozen.vjp(x, seed, spp, c), plain.vjp(x, seed, spp, c), rtol=1e-4
        )
        _, jac_frozen = frozen.jacobian(x, seed, spp, jacobian_spp=2)
        _, jac_plain = plain.jacobian(x, seed, spp, jacobian_spp=2)
        assert np.any(jac_frozen != 0, axis=0).all()
        assert flipped(jac_frozen, jac_plain) < 0.005
