"""The Mitsuba side of the bridge: render every view for a flat vector of physical parameter
values, and its derivatives (reverse: a vector-Jacobian product; forward: the full Jacobian)."""

from __future__ import annotations

import gc
import logging
import re
import weakref
from contextlib import contextmanager

import drjit as dr
import mitsuba as mi
import numpy as np

from captures.capture import Capture

from ..material import Free, Material
from .scene import MATERIAL_PREFIX, batch_sensor_dict, scene_dict

log = logging.getLogger(__name__)

#: Sensors whose derived Dr.Jit members (sample-to-camera transform, ray differentials, the
#: normalisation; thin lens also `x_fov`) are evaluated at load time (`dr::make_opaque`) but not
#: declared to Dr.Jit's frozen-function traversal (no `MI_TRAVERSE_CB` in Mitsuba 3.9.1's
#: orthographic.cpp / thinlens.cpp; perspective.cpp has one). A frozen render that reads them
#: fails with `record(): Variable ... was created before recording was started`.
_UNTRAVERSED_SENSORS = ("OrthographicCamera", "ThinLensCamera")


def _cameras(scene) -> list:
    """The scene's camera sensors: its sensor, or a `batch` sensor's children in film order."""
    sensor = scene.sensors()[0]
    if sensor.class_name() != "BatchSensor":
        return [sensor]
    props = mi.traverse(sensor).properties
    return [props[k][2] for k in props if k.startswith("view_") and k.endswith(".to_world")]


#: Every live `_Group` with such sensors among its cameras. A `batch` sensor calls its
#: children virtually, and a recorded virtual call traces every live camera of the process.
#: Measured (Dr.Jit 1.5, Mitsuba 3.9.1): with another such group loaded before it (its sensors
#: rebuilt inside the recording as well, or the recording fails), a batch's frozen reverse and
#: forward passes replayed zero or wrong derivatives (primal passes right). So a batch of such
#: cameras is frozen only until another such group is alive at one of its calls (`_Frozen`):
#: a fit's renderer is frozen, a second resolution's phases (and the first's after) are not.
_UNTRAVERSED: weakref.WeakSet = weakref.WeakSet()


def _rebuild_sensor(scene, x_fov: tuple) -> None:
    """Inside a frozen function: rebuild such sensors' derived members (a batch's children
    too) from Python scalars, so every variable the recording reads is an input or created
    while recording (a tiny kernel, replayed with the render). A no-op for other sensors."""
    for sensor, fov in zip(_cameras(scene), x_fov, strict=True):
        if sensor.class_name() not in _UNTRAVERSED_SENSORS:
            continue
        if fov is not None:  # thin lens: its evaluated x_fov feeds the projection
            mi.traverse(sensor)["x_fov"] = fov
        # a non-empty key list without "to_world": with it (or empty) Endpoint re-reads the
        # transform's value into its scalar copy, a read that a recording refuses
        sensor.parameters_changed(["x_fov"])


def _sensor_fov(scene) -> tuple:
    """Each camera's field of view as a Python float where it is a thin lens (read before any
    recording), for `_rebuild_sensor`; None for other sensors."""
    return tuple(
        float(mi.traverse(s)["x_fov"][0]) if s.class_name() == "ThinLensCamera" else None
        for s in _cameras(scene)
    )


def _reverse_pass(scene, grad_in, seed, spp: int, keys: tuple, x_fov: tuple) -> list:
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


def _forward_pass(scene, tangents: list, seed, spp: int, keys: tuple, x_fov: tuple):
    """The forward-mode derivative of the render along `tangents` (one per parameter at `keys`;
    a frozen function's body: Dr.Jit inputs only, the AD state set and cleared inside)."""
    _rebuild_sensor(scene, x_fov)
    params = mi.traverse(scene)
    for key in keys:
        dr.enable_grad(params[key])
    params.update()  # values the plugins derive in `parameters_changed` carry derivatives
    for key, tangent in zip(keys, tangents, strict=True):
        dr.set_grad(params[key], tangent)
    out = scene.integrator().render_forward(scene, params, seed=seed, spp=spp)
    for key in keys:
        dr.disable_grad(params[key])
    return out


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


def _primal(scene, seed, spp: int, x_fov: tuple):
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


#: A frozen batch of thin-lens or orthographic cameras checks this many of its first replays
#: against a plain call (see `_Frozen`).
CHECKED_REPLAYS = 2


def _same(a, b) -> bool:
    """Two renderer pass outputs (arrays, or lists of them) equal to float rounding."""
    if isinstance(a, list | tuple):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    scale = max(float(np.max(np.abs(b), initial=0.0)), 1e-30)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=1e-3, atol=1e-5 * scale))


class _Frozen:
    """`fn` as a Dr.Jit frozen function, and plainly from the first recording that fails (a
    thin-lens or orthographic camera of a scene loaded elsewhere, still alive, traced unrebuilt
    into a batch's recording). With `alone` (such a batch), plainly from the first call that
    finds another `_UNTRAVERSED` group alive, and its first `CHECKED_REPLAYS` replays are
    checked against a plain call: a batch of five thin-lens (or orthographic) views of a glazed
    sphere replayed wrong gradients from the third call on (ior -0.465 against -0.066; its
    primal right), where the cup's five and two to four of the sphere's matched exactly over
    eight calls (Dr.Jit 1.5 / Mitsuba 3.9.1; why was not found). A mismatch runs it plainly
    from then on. A module function, not a bound method (see `_Group`)."""

    def __init__(self, fn, alone: bool = False):
        self.fn, self.frozen, self.alone = fn, dr.freeze(fn), alone
        self.checked = 0

    def __call__(self, *args):
        if self.alone and len(_UNTRAVERSED) > 1:
            self.frozen = None  # for good: its plain calls replace what a recording captured
        if self.frozen is not None:
            try:
                recordings = self.frozen.n_recordings
                out = self.frozen(*args)
            except RuntimeError as err:
                if not str(err).startswith("record()"):
                    raise
                log.info("not frozen (%s): %s", self.fn.__name__, err.__cause__ or err)
                self.frozen = None
            else:
                replayed = self.frozen.n_recordings == recordings
                if not (self.alone and replayed and self.checked < CHECKED_REPLAYS):
                    return out
                self.checked += 1
                plain = self.fn(*args)
                if _same(out, plain):
                    return out
                log.warning(
                    "a frozen %s of thin-lens/orthographic cameras replayed a wrong result; "
                    "it runs unfrozen from now on",
                    self.fn.__name__,
                )
                self.frozen = None
                return plain
        return self.fn(*args)


class _Group:
    """Views rendered together: one loaded scene (a `batch` sensor when several), its parameters
    and, per free parameter, the traverse keys it sets (and emitter scales' configured values)."""

    def __init__(self, capture: Capture, views: list[int], material, free: list[Free], freeze):
        scene = scene_dict(capture.scene_of(views[0]), material, 0, 1)
        if len(views) > 1:
            scene["sensor"] = batch_sensor_dict([capture.views[i].camera for i in views], 1)
        self.views, self.scene = views, mi.load_dict(scene)
        self.params = mi.traverse(self.scene)
        name = capture.views[views[0]].name
        self.targets = [_targets(f, self.params, name) for f in free]
        self.bases = {
            k: np.asarray(self.params[k])
            for f, ks in zip(free, self.targets, strict=True)
            if f.emitter
            for k in ks
        }
        self.params.keep([k for ks in self.targets for k in ks])
        self.fov = _sensor_fov(self.scene)
        untraversed = any(s.class_name() in _UNTRAVERSED_SENSORS for s in _cameras(self.scene))
        self.untraversed = untraversed
        if untraversed:
            _UNTRAVERSED.add(self)
        alone = untraversed and len(views) > 1

        def wrap(fn):
            return _Frozen(fn, alone) if freeze else fn

        # module functions, not bound methods: a Renderer holding its own bound methods is a
        # reference cycle, freed only by the cyclic collector, possibly inside a later recording
        self.primal, self.reverse = wrap(_primal), wrap(_reverse_pass)
        self.forward = wrap(_forward_pass)


class Renderer:
    """Loaded scenes of a capture's views with one material; parameters `free` are set from flat
    physical vectors. Scalars stay opaque (the plugins mark them), so changing values or the
    sample count between calls does not recompile kernels. All outputs are float32, views
    flattened and concatenated in the capture's order.

    Views that share the scene's lights and their size render together through one `batch`
    sensor (side by side in one film): one kernel per pass for all of them, where one scene per
    view compiles one per view (the cup's reverse pass: ~15 s of LLVM each on 2 cores). Views
    with their own lights (photometric stereo) get a scene each.

    With `freeze` (the default) primal renders, reverse passes and the Jacobian's forward passes
    are Dr.Jit frozen functions: recorded at the first call per spp, replayed after without
    re-tracing the path tracer in Python (measured on the Cycles sphere at 8 spp: 1.7x faster
    primal, 2.1x faster reverse pass; a Jacobian of two 48x36 views 4-6x faster). Thin-lens and
    orthographic cameras, which Mitsuba 3.9 does not declare to the recording, are rebuilt
    inside it (`_rebuild_sensor`). A batch of them is frozen while it is the one scene with such
    cameras alive (`_UNTRAVERSED`; the cup's five thin-lens views of 64x56: an Adam step at 8
    spp 0.69-0.82 s frozen, 1.19 s re-traced, same run). A function whose recording fails runs
    unfrozen from then on (`_Frozen`). Nothing is frozen when a texture is free (replaying a
    frozen render after a bitmap's data was replaced crashed: segmentation fault, Dr.Jit 1.5 /
    Mitsuba 3.9, a 16x16 mask texture)."""

    def __init__(
        self,
        capture: Capture,
        material: Material | dict,
        free: list[Free],
        freeze: bool = True,
        batch: bool = True,
    ):
        self.free = free
        views = capture.views
        self.shapes = [(v.camera.height, v.camera.width, 3) for v in views]
        self.size = int(sum(np.prod(s) for s in self.shapes))
        self.n_params = sum(f.size for f in free)
        batched = (
            batch
            and len(views) > 1
            and all(v.lights is None for v in views)
            and len({s[:2] for s in self.shapes}) == 1
        )
        freeze = freeze and not any(f.shape for f in free)
        groups = [list(range(len(views)))] if batched else [[i] for i in range(len(views))]
        self.groups = [_Group(capture, g, material, free, freeze) for g in groups]
        #: A group with thin-lens or orthographic cameras: its batch is frozen only while no
        #: other such group is alive (`Problem.release` frees this one when it is done)
        self.untraversed = any(g.untraversed for g in self.groups)
        self.scenes = [g.scene for g in self.groups]
        self.params = [g.params for g in self.groups]

    def _split(self, group: _Group, image) -> list[np.ndarray]:
        """A group's image (views side by side) as its views' flat images."""
        image = np.asarray(image, np.float32)[..., :3]
        w = self.shapes[group.views[0]][1]
        return [image[:, k * w : (k + 1) * w].ravel() for k in range(len(group.views))]

    def _join(self, group: _Group, flat_views: list[np.ndarray]) -> np.ndarray:
        """Views' flat images (cotangents) side by side as the group's image."""
        shapes = [self.shapes[v] for v in group.views]
        parts = [f.reshape(s) for f, s in zip(flat_views, shapes, strict=True)]
        return np.ascontiguousarray(np.concatenate(parts, axis=1), np.float32)

    def _set(self, g: int | _Group, values: np.ndarray, grad: bool = False) -> None:
        """Set a group's parameters from a flat physical vector (with `grad`, AD-enabled before
        the update, so values the plugins derive in `parameters_changed` carry derivatives)."""
        group = self.groups[g] if isinstance(g, int) else g
        params, i = group.params, 0
        for f, keys in zip(self.free, group.targets, strict=True):
            chunk = values[i : i + f.size]
            for key in keys:
                current = params[key]
                if f.emitter:
                    value = _like(current, group.bases[key] * float(chunk[0]))
                else:
                    value = _like(current, chunk)
                if grad:
                    dr.enable_grad(value)
                params[key] = value
            i += f.size
        params.update()

    def _tangent(self, group: _Group, f: Free, key: str, component: int | None):
        """d params[key] / d (component of f) in a group (zero when `component` is None), as an
        opaque value: every column's forward pass then traces the same kernel, compiled once."""
        if f.emitter:
            tangent = group.bases[key] * (0.0 if component is None else 1.0)
        else:
            tangent = np.zeros(f.size)
            if component is not None:
                tangent[component] = 1.0
        value = _like(group.params[key], tangent)
        dr.make_opaque(value)
        return value

    def _offsets(self) -> list[int]:
        return list(np.cumsum([0] + [int(np.prod(s)) for s in self.shapes]))

    def render(self, values: np.ndarray, seed: int, spp: int) -> np.ndarray:
        out = []
        for g, group in enumerate(self.groups):
            self._set(group, values)
            seed_g = mi.UInt32(int(seed) + 7919 * g)
            with _no_gc():
                image = group.primal(group.scene, seed_g, spp, group.fov)
            out += self._split(group, image)
        return np.concatenate(out)

    def vjp(self, values: np.ndarray, seed: int, spp: int, cotangent: np.ndarray) -> np.ndarray:
        """Gradient of `<cotangent, render(values)>` with respect to `values`."""
        grad = np.zeros(self.n_params, np.float32)
        offsets = self._offsets()
        for g, group in enumerate(self.groups):
            self._set(group, values)
            flat = [cotangent[offsets[v] : offsets[v + 1]] for v in group.views]
            grad_in = mi.TensorXf(self._join(group, flat))
            seed_g = mi.UInt32(int(seed) + 7919 * g + GRAD_SEED_OFFSET)
            keys = tuple(k for ks in group.targets for k in ks)
            with _no_gc():
                grads = iter(group.reverse(group.scene, grad_in, seed_g, spp, keys, group.fov))
            i = 0
            for f, ks in zip(self.free, group.targets, strict=True):
                for key in ks:
                    d = np.asarray(next(grads), np.float64)
                    if f.emitter:  # d/ds of base * s
                        grad[i] += float(np.sum(d.reshape(-1) * group.bases[key].reshape(-1)))
                    else:
                        grad[i : i + f.size] += np.ravel(d).astype(np.float32)
                i += f.size
            self._drop_ad(group, values)
        return grad

    def _drop_ad(self, group: _Group, values: np.ndarray) -> None:
        """Set the values again without derivatives after a pass that enabled them: unfrozen, a
        value the plugins derived from a differentiated one (a bitmap's mean) keeps its AD graph
        in the scene, and a later frozen pass of another Renderer in this process (a Ray worker's
        next fit) fails on that stale graph (`ad_traverse(): ... outside of the current
        dr.isolate_grad() scope`)."""
        self._set(group, values)

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
        offsets = self._offsets()
        for g, group in enumerate(self.groups):
            self._set(group, values)
            keys = tuple(k for ks in group.targets for k in ks)
            seed_g = mi.UInt32(int(j_seed) + 7919 * g)
            column = 0
            for f in self.free:
                for c in range(f.size):
                    # every parameter gets a tangent (zero but this column's): one AD graph, one
                    # kernel for all columns (a tangent on one parameter alone is a new kernel,
                    # ~10 s of LLVM each for the cup)
                    tangents = [
                        self._tangent(group, other, key, c if other is f else None)
                        for other, other_keys in zip(self.free, group.targets, strict=True)
                        for key in other_keys
                    ]
                    with _no_gc():
                        out = group.forward(group.scene, tangents, seed_g, j_spp, keys, group.fov)
                    for v, part in zip(group.views, self._split(group, out), strict=True):
                        jac[offsets[v] : offsets[v + 1], column] = part
                    column += 1
            self._drop_ad(group, values)
        return image, jac
