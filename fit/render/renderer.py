"""The Mitsuba side of the bridge: render every view for a flat vector of physical parameter
values, and its derivatives (reverse: a vector-Jacobian product; forward: the full Jacobian)."""

from __future__ import annotations

import gc
import re
from contextlib import contextmanager

import drjit as dr
import mitsuba as mi
import numpy as np

from captures.capture import Capture

from ..material import Free
from .scene import MATERIAL_PREFIX, scene_dict

#: Sensors whose derived Dr.Jit members (sample-to-camera transform, ray differentials, the
#: normalisation; thin lens also `x_fov`) are evaluated at load time (`dr::make_opaque`) but not
#: declared to Dr.Jit's frozen-function traversal (no `MI_TRAVERSE_CB` in Mitsuba 3.9.1's
#: orthographic.cpp / thinlens.cpp; perspective.cpp has one). A frozen render that reads them
#: fails with `record(): Variable ... was created before recording was started`.
_UNTRAVERSED_SENSORS = ("OrthographicCamera", "ThinLensCamera")


def _rebuild_sensor(scene, x_fov: float | None) -> None:
    """Inside a frozen function: rebuild such a sensor's derived members from Python scalars, so
    every variable the recording reads is an input or created while recording (a tiny kernel,
    replayed with the render). A no-op for other sensors."""
    sensor = scene.sensors()[0]
    if sensor.class_name() not in _UNTRAVERSED_SENSORS:
        return
    if x_fov is not None:  # thin lens: its evaluated x_fov feeds the projection
        mi.traverse(sensor)["x_fov"] = x_fov
    # a non-empty key list without "to_world": with it (or empty) Endpoint re-reads the
    # transform's value into its scalar copy, a read that a recording refuses
    sensor.parameters_changed(["x_fov"])


def _sensor_fov(scene) -> float | None:
    """A thin-lens sensor's field of view as a Python float (read before any recording), for
    `_rebuild_sensor`; None for other sensors."""
    sensor = scene.sensors()[0]
    if sensor.class_name() != "ThinLensCamera":
        return None
    return float(mi.traverse(sensor)["x_fov"][0])


def _reverse_pass(scene, grad_in, seed, spp: int, keys: tuple, x_fov: float | None = None) -> list:
    """Gradients of `<grad_in, render>` with respect to the parameters at `keys` (a frozen
    function's body: Dr.Jit inputs only, the AD state set and cleared inside)."""
    _rebuild_sensor(scene, x_fov)
    params = mi.traverse(scene)
    for key in keys:
        dr.enable_grad(params[key])
    params.update()
    scene.integrator().render_backward(scene, params, grad_in, seed=seed, spp=spp)
    grads = [dr.grad(params[key]) for key in keys]
    for key in keys:
        dr.disable_grad(params[key])
    return grads


@contextmanager
def _no_gc():
    """Keep Python's cyclic garbage collector from running during a frozen call. Freeing a loaded
    `mi.Scene` (or any Dr.Jit array made from NumPy) while Dr.Jit 1.5 records a frozen function
    aborts the process (`RecordThreadState::enqueue_host_func(): this function cannot be
    recorded!`, thrown from a destructor: std::terminate, not a Python exception), and the
    collector can run at any allocation inside the recording and free, e.g., an earlier
    Renderer's scenes."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


def _primal(scene, seed, spp: int, x_fov: float | None = None):
    _rebuild_sensor(scene, x_fov)
    return mi.render(scene, spp=spp, seed=seed)


#: Traverse keys of emitter radiance by scale: every light's, the environment's.
_EMITTER_KEYS = {
    "lights": re.compile(r"light_\d+\.(emitter\.radiance|intensity|irradiance)\.value"),
    "environment": re.compile(r"environment\.(radiance\.value|data)"),
}


def _targets(f: Free, params, view: str) -> list[str]:
    """The traverse keys `f` sets in one view's scene."""
    if f.emitter is None:
        key = MATERIAL_PREFIX + f.traverse
        keys = [key] if key in params else []
    else:
        keys = [k for k in params.keys() if _EMITTER_KEYS[f.emitter].fullmatch(k)]
    if not keys:
        raise KeyError(f"{f.key}: not in the scene of view {view} (nothing to fit)")
    return keys


def _like(current, values):
    """`values` (numpy) as the Dr.Jit type of `current`."""
    values = np.asarray(values, np.float32)
    if isinstance(current, mi.TensorXf):
        return mi.TensorXf(values.reshape(current.shape))
    if values.size == 1:
        return type(current)(float(values.reshape(-1)[0]))
    return type(current)(*[float(x) for x in values.reshape(-1)])


#: The reverse pass (`vjp`) uses the seed plus this offset. Paths shared between the primal image
#: and its gradient would correlate the residual with the gradient: the gradient of E[(I - T)^2]
#: would pick up the gradient of the variance and pull fits towards low-noise parameters (Mitsuba's
#: own `mi.render` decorrelates the same way with `seed_grad`). Measured on the Cycles sphere:
#: alpha +9 % and pigment -0.03 with shared seeds, -1.9 % and +0.001 decorrelated. The Jacobian
#: keeps the image's seed unless asked for a decorrelated one (`jacobian_spp`).
GRAD_SEED_OFFSET = 0x5EED1


class Renderer:
    """Loaded scenes of a capture's views with one material; parameters `free` are set from flat
    physical vectors. Scalars stay opaque (the plugins mark them), so changing values or the
    sample count between calls does not recompile kernels. All outputs are float32, views
    flattened and concatenated.

    With `freeze` (the default) primal renders and reverse passes are Dr.Jit frozen functions,
    one per view: recorded at the first call per spp, replayed after without re-tracing the path
    tracer in Python (measured on the Cycles sphere at 8 spp: 1.7x faster primal, 2.1x faster
    reverse pass; identical values). Forward-mode Jacobians are not frozen, nor anything when a
    texture is free: replaying a frozen render after a bitmap's data was replaced crashed
    (segmentation fault, Dr.Jit 1.5 / Mitsuba 3.9, measured with a 16x16 mask texture)."""

    def __init__(self, capture: Capture, material: dict, free: list[Free], freeze: bool = True):
        self.free = free
        self.scenes = [
            mi.load_dict(scene_dict(capture.scene_of(i), material, 0, 1))
            for i in range(len(capture.views))
        ]
        self.params = [mi.traverse(s) for s in self.scenes]
        # per view, per free parameter: the traverse keys it sets, and for emitter scales the
        # configured values they multiply
        self.targets, self.bases = [], []
        for v, params in enumerate(self.params):
            targets = [_targets(f, params, capture.views[v].name) for f in free]
            self.targets.append(targets)
            self.bases.append(
                {
                    k: np.asarray(params[k])
                    for f, ks in zip(free, targets, strict=True)
                    if f.emitter
                    for k in ks
                }
            )
            params.keep([k for ks in targets for k in ks])
        self.shapes = [(v.camera.height, v.camera.width, 3) for v in capture.views]
        self.size = int(sum(np.prod(s) for s in self.shapes))
        self.n_params = sum(f.size for f in free)
        freeze = freeze and not any(f.shape for f in free)
        wrap = dr.freeze if freeze else (lambda f: f)
        self._primal = [wrap(_primal) for _ in self.scenes]
        # a module function, not a bound method: a Renderer holding its own bound methods is a
        # reference cycle, freed only by the cyclic collector, possibly inside a later recording
        self._reverse = [wrap(_reverse_pass) for _ in self.scenes]
        self._fov = [_sensor_fov(s) for s in self.scenes]

    def _set(self, v: int, values: np.ndarray, grad: bool = False) -> None:
        """Set view `v`'s parameters from a flat physical vector (with `grad`, AD-enabled before
        the update, so values the plugins derive in `parameters_changed` carry derivatives)."""
        params, i = self.params[v], 0
        for f, keys in zip(self.free, self.targets[v], strict=True):
            chunk = values[i : i + f.size]
            for key in keys:
                current = params[key]
                if f.emitter:
                    value = _like(current, self.bases[v][key] * float(chunk[0]))
                else:
                    value = _like(current, chunk)
                if grad:
                    dr.enable_grad(value)
                params[key] = value
            i += f.size
        params.update()

    def _tangent(self, v: int, f: Free, key: str, component: int):
        """d params[key] / d (component of f) at view v."""
        if f.emitter:
            return _like(self.params[v][key], self.bases[v][key])
        tangent = np.zeros(f.size)
        tangent[component] = 1.0
        return _like(self.params[v][key], tangent)

    def render(self, values: np.ndarray, seed: int, spp: int) -> np.ndarray:
        out = []
        for v, scene in enumerate(self.scenes):
            self._set(v, values)
            seed_v = mi.UInt32(int(seed) + 7919 * v)
            with _no_gc():
                image = self._primal[v](scene, seed_v, spp, self._fov[v])
            out.append(np.asarray(image, dtype=np.float32)[..., :3].ravel())
        return np.concatenate(out)

    def vjp(self, values: np.ndarray, seed: int, spp: int, cotangent: np.ndarray) -> np.ndarray:
        """Gradient of `<cotangent, render(values)>` with respect to `values`."""
        grad = np.zeros(self.n_params, np.float32)
        offset = 0
        for v, scene in enumerate(self.scenes):
            n = int(np.prod(self.shapes[v]))
            self._set(v, values)
            grad_in = mi.TensorXf(
                np.ascontiguousarray(
                    cotangent[offset : offset + n].reshape(self.shapes[v]), np.float32
                )
            )
            seed_v = mi.UInt32(int(seed) + 7919 * v + GRAD_SEED_OFFSET)
            keys = tuple(k for ks in self.targets[v] for k in ks)
            with _no_gc():
                grads = iter(self._reverse[v](scene, grad_in, seed_v, spp, keys, self._fov[v]))
            i = 0
            for f, ks in zip(self.free, self.targets[v], strict=True):
                for key in ks:
                    g = np.asarray(next(grads), np.float64)
                    if f.emitter:  # d/ds of base * s
                        grad[i] += float(np.sum(g.reshape(-1) * self.bases[v][key].reshape(-1)))
                    else:
                        grad[i : i + f.size] += np.ravel(g).astype(np.float32)
                i += f.size
            offset += n
        return grad

    def jacobian(
        self, values: np.ndarray, seed: int, spp: int, jacobian_spp: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(image, d image / d values) with one forward-mode render per parameter component.

        By default all with the image's seed and spp: the exact Jacobian of this seed's image (what
        LM needs to converge on a fixed objective, whose optimum is biased at low spp: the noise's
        own gradient enters). With `jacobian_spp` the Jacobian is rendered with a decorrelated seed
        at that spp: then `J^T r` is an unbiased gradient, and a cheap Jacobian preconditions an
        expensive, accurate residual."""
        image = self.render(values, seed, spp)
        j_seed, j_spp = (
            (seed, spp) if jacobian_spp is None else (seed + GRAD_SEED_OFFSET, jacobian_spp)
        )
        jac = np.zeros((self.size, self.n_params), np.float32)
        offset = 0
        for v, scene in enumerate(self.scenes):
            n = int(np.prod(self.shapes[v]))
            params, column = self.params[v], 0
            for f, keys in zip(self.free, self.targets[v], strict=True):
                for c in range(f.size):
                    self._set(v, values, grad=True)
                    for key in keys:
                        dr.set_grad(params[key], self._tangent(v, f, key, c))
                    out = scene.integrator().render_forward(
                        scene, params, seed=int(j_seed) + 7919 * v, spp=j_spp
                    )
                    jac[offset : offset + n, column] = np.asarray(out, np.float32)[..., :3].ravel()
                    column += 1
            self._set(v, values)  # drop the AD state
            offset += n
        return image, jac
