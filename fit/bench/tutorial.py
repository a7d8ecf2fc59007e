"""The loop a Mitsuba user writes today: a tutorial's optimisation loop, natively (Mitsuba's own
Adam on the raw values, no JAX), the baseline the grid and the versus table time."""

from __future__ import annotations

import time

import mitsuba as mi
import numpy as np

from ..render import load_scene, scene_dict

#: The tutorial loop, pinned: Mitsuba's own Adam on raw values, 200 iterations at 16 spp and lr
#: 0.05, then 100 at 64 spp and lr 0.01; iteration i renders with seed i, its gradient with seed
#: i + TUTORIAL_GRAD_SEED; values clipped to the parameters' bounds after each step.
TUTORIAL = ((200, 16, 0.05), (100, 64, 0.01))
TUTORIAL_GRAD_SEED = 1_000_003
TUTORIAL_SEED_STRIDE = 100_000
#: The tutorial loop's warm-up before a timed run: one iteration of each stage (it compiles the
#: kernels the timed run needs).
TUTORIAL_WARM_UP = ((1, 16, 0.05), (1, 64, 0.01))


def tutorial_loop(
    problem, start: dict, stages=TUTORIAL, seed: int = 0, record=None, every: int = 10
) -> tuple[float, dict, int]:
    """The loop of a Mitsuba tutorial, natively (no JAX, no transforms, no freezing): one scene
    per view, `mi.ad.Adam` on the raw parameter values, `dr.backward` of the weighted squared
    error through `mi.render` with a decorrelated `seed_grad`, clipped to bounds. Returns its
    wall time until the final values are read (Dr.Jit evaluates lazily: a loop's iterations
    return before their work is done), the values, and the renders (primal and adjoint each
    count one per view). With `seed` k iteration i renders with seed k x TUTORIAL_SEED_STRIDE + i
    (k = 0: the pinned seeds); `record(iteration, seconds, values)` is called every `every`
    iterations (reading the values waits for that iteration's kernels)."""
    import drjit as dr

    from ..render import MATERIAL_PREFIX

    capture = problem.capture
    _, sqrt_w = problem.target()
    scenes, params, targets, weights, offset = [], [], [], [], 0
    for i, view in enumerate(capture.views):
        scenes.append(load_scene(scene_dict(capture.scene_of(i), problem.material, 0, 16)))
        params.append(mi.traverse(scenes[-1]))
        targets.append(mi.TensorXf(view.image))
        size = view.image.size
        weights.append(mi.TensorXf(sqrt_w[offset : offset + size].reshape(view.image.shape)))
        offset += size
    keys = [MATERIAL_PREFIX + f.traverse for f in problem.free]

    def values():
        out = {}
        for f, key in zip(problem.free, keys, strict=True):
            value = np.ravel(np.asarray(opt[key], np.float64))
            out[f.key] = value.tolist() if f.size > 1 else float(value[0])
        return out

    began = time.perf_counter()
    opt = mi.ad.Adam(lr=stages[0][2])
    for f, key in zip(problem.free, keys, strict=True):
        opt[key] = type(params[0][key])(*np.ravel(start[f.key]).tolist())
    it, renders = 0, 0
    for iterations, spp, lr in stages:
        opt.set_learning_rate(lr)
        for _ in range(iterations):
            loss = mi.Float(0.0)
            for scene, p, target, weight in zip(scenes, params, targets, weights, strict=True):
                p.update(opt)
                base = seed * TUTORIAL_SEED_STRIDE + it
                image = mi.render(scene, p, spp=spp, seed=base, seed_grad=base + TUTORIAL_GRAD_SEED)
                loss += dr.sum(dr.square((image - target) * weight), axis=None)
                renders += 2
            dr.backward(loss)
            opt.step()
            for f, key in zip(problem.free, keys, strict=True):
                opt[key] = dr.clip(opt[key], f.spec.lower, f.spec.upper)
            it += 1
            if record is not None and it % every == 0:
                record(it, time.perf_counter() - began, values())
    final = values()
    return time.perf_counter() - began, final, renders
