"""The Mitsuba side of the bridge: render every view for a flat vector of physical parameter
values, and its derivatives (reverse: a vector-Jacobian product; forward: the full Jacobian)."""

from __future__ import annotations

import functools
import gc
import logging
import re
import threading
from contextlib import contextmanager

import drjit as dr
import mitsuba as mi
import numpy as np
from mitsuba.ad.integrators.common import ADIntegrator, RBIntegrator

from captures.capture import Capture
from captures.scene import bounding_sphere

from ..material import Free, Material
from .scene import MATERIAL_PREFIX, batch_sensor_dict, load_scene, scene_dict, sensor_dict

log = logging.getLogger(__name__)

#: Sensors whose derived Dr.Jit members (sample-to-camera transform, ray differentials, the
#: normalisation; thin lens also `x_fov`) are evaluated at load time (`dr::make_opaque`) but not
#: declared to Dr.Jit's frozen-function traversal (no `MI_TRAVERSE_CB` in Mitsuba 3.9.1's
#: orthographic.cpp / thinlens.cpp; perspective.cpp has one). A frozen render that reads them
#: fails with `record(): Variable ... was created before recording was started`.
_UNTRAVERSED_SENSORS = ("OrthographicCamera", "ThinLensCamera")


def _cameras(scene, sensor: int) -> list:
    """The scene's camera sensors at index `sensor`: it, or a `batch` sensor's children in film
    order."""
    sensor = scene.sensors()[sensor]
    if sensor.class_name() != "BatchSensor":
        return [sensor]
    props = mi.traverse(sensor).properties
    return [props[k][2] for k in props if k.startswith("view_") and k.endswith(".to_world")]


#: A thin lens's members its kernels read, set opaque inside the recording from Python floats:
#: `x_fov` is evaluated at load but not declared to the recording; `aperture_radius` and
#: `focus_distance` are host literals at load, baked into the kernel (a kernel per view).
_THIN_LENS_FLOATS = ("x_fov", "aperture_radius", "focus_distance")


def _rebuild_sensor(scene, sensor: int, floats: tuple) -> None:
    """Inside a frozen function: rebuild such sensors' derived members from Python scalars, so
    every variable the recording reads is an input or created while recording (a tiny kernel,
    replayed with the render). A no-op for other sensors."""
    for camera, values in zip(_cameras(scene, sensor), floats, strict=True):
        if camera.class_name() not in _UNTRAVERSED_SENSORS:
            continue
        params = mi.traverse(camera)
        for key, value in zip(_THIN_LENS_FLOATS, values or (), strict=False):
            params[key] = dr.opaque(mi.Float, value)
        # a non-empty key list without "to_world": with it (or empty) Endpoint re-reads the
        # transform's value into its scalar copy, a read that a recording refuses
        camera.parameters_changed(["x_fov"])


def _sensor_floats(scene, sensor: int) -> tuple:
    """Each camera's `_THIN_LENS_FLOATS` as Python floats where it is a thin lens (read before
    any recording), for `_rebuild_sensor`; None for other sensors."""
    return tuple(
        tuple(float(mi.traverse(c)[key][0]) for key in _THIN_LENS_FLOATS)
        if c.class_name() == "ThinLensCamera"
        else None
        for c in _cameras(scene, sensor)
    )


@contextmanager
def _differentiated(scene, keys: tuple, sensor: int, floats: tuple):
    """A frozen pass's parameters (`mi.traverse`) with derivatives at `keys` enabled, then
    cleared (the AD state set and cleared inside the frozen function's body; Dr.Jit inputs only)."""
    _rebuild_sensor(scene, sensor, floats)
    params = mi.traverse(scene)
    for key in keys:
        dr.enable_grad(params[key])
    params.update()  # values the plugins derive in `parameters_changed` carry derivatives
    try:
        yield params
    finally:
        for key in keys:
            dr.disable_grad(params[key])


def _reverse_pass(scene, grad_in, seed, spp: int, keys: tuple, sensor: int, floats: tuple) -> list:
    """Gradients of `<grad_in, render>` with respect to the parameters at `keys` (a frozen
    function's body)."""
    with _differentiated(scene, keys, sensor, floats) as params:
        scene.integrator().render_backward(scene, params, grad_in, sensor, seed=seed, spp=spp)
        return [dr.grad(params[key]) for key in keys]


def imaged(integrator) -> bool:
    """Whether `_backward_with_image` can stand in for `integrator`'s reverse pass: a path-replay
    integrator whose `render_backward` is Mitsuba's `RBIntegrator`'s own (`prb`, `prb_basic`,
    `prbvolpath`; not the projective ones, which add boundary terms), without AOVs."""
    own = getattr(type(integrator), "render_backward", None)
    return own is RBIntegrator.render_backward and not integrator.aov_names()


def _camera_samples(integrator, scene, sensor: int, seed, spp: int):
    """`(film, sampler, spp, rays, their weights, their film positions)` of a sensor: the start
    of Mitsuba 3.9's `RBIntegrator.render_forward`, the same for the same seed and spp."""
    camera = scene.sensors()[sensor]
    sampler, spp = integrator.prepare(camera, seed, spp, [])
    return (camera.film(), sampler, spp, *integrator.sample_rays(scene, camera, sampler))


def _develop(film, pos, value, spp: int, ray, valid=None):
    """The film's image of samples' `value`s at `pos` (`RBIntegrator`'s splatting; alpha 1
    where `valid` is None)."""
    alpha = 1.0 if valid is None else dr.select(valid, mi.Float(1), mi.Float(0))
    block = film.create_block()
    block.set_coalesce(block.coalesce() and spp >= 4)
    ADIntegrator._splat_to_block(
        block, film, pos, value=value, weight=1.0, alpha=alpha, aovs=[],
        wavelengths=ray.wavelengths,
    )  # fmt: skip
    film.put_block(block)
    return film.develop()


def _backward_with_image(integrator, scene, grad_in, sensor: int, seed, spp: int):
    """`integrator.render_backward(scene, params, grad_in, sensor, seed, spp)` (an `imaged`
    integrator's: the steps of Mitsuba 3.9's `RBIntegrator.render_backward`) that also returns
    the image of its own primal pass, the one `mi.render` renders at this seed and spp (its
    radiance stored between two kernels, where `mi.render` has one: now and then a branch's
    float rounding flips a sample, 2 of 1296 pixels on a thin-lens batch): the image and the
    gradient then share their paths, for one pass's cost instead of two."""
    with dr.suspend_grad():
        film, sampler, spp, ray, weight, pos = _camera_samples(integrator, scene, sensor, seed, spp)
        # each sample's adjoint radiance: `grad_in` back through the splatting and the division
        with dr.resume_grad():
            ones = dr.full(mi.Spectrum, 1.0, dr.width(ray))
            dr.enable_grad(ones)
            image = _develop(film, pos, ones * weight, spp, ray)
            dr.set_grad(image, grad_in)
            dr.enqueue(dr.ADMode.Backward, image)
            dr.traverse(dr.ADMode.Backward)
            adjoint = dr.grad(ones)
        film.clear()
        common = dict(scene=scene, ray=ray, depth=mi.UInt32(0), active=mi.Bool(True))
        radiance, valid, _, state = integrator.sample(
            mode=dr.ADMode.Primal, sampler=sampler.clone(), δL=None, δaovs=None, state_in=None,
            **common,
        )  # fmt: skip
        # stored: the image's splatting evaluates the primal pass in a kernel of its own, and
        # the reverse pass would otherwise trace it again into its own kernel
        dr.eval(radiance, valid, state)
        image = _develop(film, pos, radiance * weight, spp, ray, valid)
        integrator.sample(
            mode=dr.ADMode.Backward, sampler=sampler, δL=adjoint, δaovs=[], state_in=state,
            **common,
        )  # fmt: skip
        dr.eval(image)  # with the reverse pass's side effects (the parameters' gradients)
    return image


def _reverse_pass_imaged(scene, grad_in, seed, spp: int, keys: tuple, sensor: int, floats: tuple):
    """`_reverse_pass` that also returns its primal pass's image (`_backward_with_image`):
    `(image, gradients)`."""
    with _differentiated(scene, keys, sensor, floats) as params:
        image = _backward_with_image(scene.integrator(), scene, grad_in, sensor, seed, spp)
        return image, [dr.grad(params[key]) for key in keys]


def _forward_pass(scene, tangents: list, seed, spp: int, keys: tuple, sensor: int, floats: tuple):
    """The forward-mode derivative of the render along `tangents` (one per parameter at `keys`;
    a frozen function's body)."""
    with _differentiated(scene, keys, sensor, floats) as params:
        for key, tangent in zip(keys, tangents, strict=True):
            dr.set_grad(params[key], tangent)
        return scene.integrator().render_forward(scene, params, sensor, seed=seed, spp=spp)


def _jacobian_primal(scene, seed, spp: int, sensor: int, floats: tuple):
    """`(image, each sample's radiance)`: the primal pass of Mitsuba 3.9's
    `RBIntegrator.render_forward` (`imaged` integrators), kept for all of a Jacobian's columns
    (`_jacobian_column`), where that method renders it again for each. The image is the one
    `mi.render` renders at this seed and spp (its radiance stored between kernels, as in
    `_backward_with_image`)."""
    _rebuild_sensor(scene, sensor, floats)
    integrator = scene.integrator()
    with dr.suspend_grad():
        film, sampler, spp, ray, weight, pos = _camera_samples(integrator, scene, sensor, seed, spp)
        radiance, valid, _, state = integrator.sample(
            mode=dr.ADMode.Primal, scene=scene, sampler=sampler, ray=ray, depth=mi.UInt32(0),
            δL=None, δaovs=None, state_in=None, active=mi.Bool(True),
        )  # fmt: skip
        dr.eval(state)
        return _develop(film, pos, radiance * weight, spp, ray, valid), state


def _jacobian_column(scene, tangents, state, seed, spp: int, keys: tuple, sensor: int, floats):
    """The forward-mode derivative of the render along `tangents` (as `_forward_pass`) from the
    primal pass's radiance `state` at the same seed and spp (`_jacobian_primal`): the forward
    pass of `RBIntegrator.render_forward` alone, one recording replayed for every column."""
    with _differentiated(scene, keys, sensor, floats) as params:
        for key, tangent in zip(keys, tangents, strict=True):
            dr.set_grad(params[key], tangent)
        integrator = scene.integrator()
        with dr.suspend_grad():
            film, sampler, spp, ray, weight, pos = _camera_samples(
                integrator, scene, sensor, seed, spp
            )
            δL, valid, _, _ = integrator.sample(
                mode=dr.ADMode.Forward, scene=scene, sampler=sampler, ray=ray,
                depth=mi.UInt32(0), δL=None, δaovs=None, state_in=state, active=mi.Bool(True),
            )  # fmt: skip
            return _develop(film, pos, δL * weight, spp, ray, valid)


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


def _primal(scene, seed, spp: int, sensor: int, floats: tuple):
    _rebuild_sensor(scene, sensor, floats)
    return mi.render(scene, sensor=sensor, spp=spp, seed=seed)


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


def _with_texels(material, free: list[Free]):
    """`material`'s dict with the bitmaps of its free textures read by the `texels` plugin
    (`materials.texels`): its texels are one tensor, written between frozen renders. (Mitsuba's
    `bitmap` keeps a second copy, and replays of frozen renders read it stale.)"""
    if not isinstance(material, Material):
        return material
    files = {str(material.params[f.key].texture) for f in free if f.shape}

    def swap(value):
        if not isinstance(value, dict):
            return value
        out = {k: swap(v) for k, v in value.items()}
        if out.get("type") == "bitmap" and str(out.get("filename")) in files:
            out["type"] = "texels"
        return out

    return swap(material.bsdf) if files else material


def _write_texels(texels, values) -> None:
    """Write a free texture's texels (a `texels` plugin's tensor, `_with_texels`) in place: a
    scatter into the same array. A new tensor assigned instead, to this plugin or to Mitsuba's
    `bitmap`, made frozen renders replay stale texels: wrong images from the third call on, and
    wrong gradients (0 for a mask threshold whose gradient was -53), on perspective and
    orthographic views alike (Dr.Jit 1.5 / Mitsuba 3.9.1, LLVM). Written in place, primal and
    reverse passes replay what unfrozen ones render (`tests/fit/test_frozen_textures.py`)."""
    flat = mi.Float(np.asarray(values, np.float32).reshape(-1))
    dr.scatter(texels.array, flat, dr.arange(mi.UInt32, dr.width(flat)))


def _owned(tensor):
    """`tensor` (made from NumPy) in memory of Dr.Jit's own: written into a new array. Dr.Jit
    maps a NumPy array's memory, and a frozen function records again when a mapped input's
    alignment changes, which it does from one NumPy array to the next (the cup's reverse pass:
    11 recordings of its 5 sensors; `dr.copy` kept the mapping)."""
    out = dr.zeros(mi.TensorXf, tensor.shape)
    dr.scatter(out.array, tensor.array, dr.arange(mi.UInt32, dr.width(tensor.array)))
    dr.eval(out)
    return out


def _like(current, values):
    """`values` (numpy) as the Dr.Jit type of `current`."""
    values = np.asarray(values, np.float32)
    if isinstance(current, mi.TensorXf):
        return _owned(mi.TensorXf(values.reshape(current.shape)))
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


#: A frozen function that records more than this many times for the same host arguments (spp,
#: sensor, keys) runs plainly from then on. Dr.Jit records a key again once or twice as it makes
#: changing literals opaque (the cup's thin-lens sensors); a thin-lens view beside a pinhole or
#: orthographic one in a scene made it record on every call ("dry-running the recording
#: failed"), printing a warning per call from its 10th recording and running about 20 % slower
#: than plain (a user's report, two 48x36 views).
RERECORD_LIMIT = 8


#: One render at a time in a process. The JAX bridge's callbacks run on XLA's threads, and
#: callbacks that do not depend on each other run at once: `gn`'s control gradient, whose reverse
#: pass does not need the step's image, started it while that image still rendered on another
#: thread (seen: a reverse pass entered while a render ran). A `Renderer` sets its scenes' values
#: before each pass, and Dr.Jit used from two threads at once aborted (`jit_var(...): unknown
#: variable!`; the process then hung): the cup's main job, two runs in six, 2026-12-02.
_ONE_AT_A_TIME = threading.RLock()


def _serialised(method):
    @functools.wraps(method)
    def wrapper(*args, **kwargs):
        with _ONE_AT_A_TIME:
            return method(*args, **kwargs)

    return wrapper


class _Frozen:
    """`fn` as a Dr.Jit frozen function, and plainly from the first recording that fails (a
    thin-lens or orthographic camera of another scene, still alive, traced unrebuilt into a
    `batch` sensor's recording: its virtual call on the cameras traces every live camera of the
    process). A module function, not a bound method (see `_Group`). Dr.Jit warns (on stderr,
    to the user) once a function has `warn_after` recordings: it records once per sensor and
    spp, so a group of several sensors allows as many times Dr.Jit's default 10."""

    def __init__(self, fn, sensors: int = 1):
        self.fn, self.frozen = fn, dr.freeze(fn, warn_after=10 * sensors)
        self.recorded: dict = {}  # recordings by host arguments (spp, sensor, keys)

    def __call__(self, *args):
        if self.frozen is None:
            return self.fn(*args)
        before = self.frozen.n_recordings
        try:
            out = self.frozen(*args)
        except RuntimeError as err:
            if not str(err).startswith("record()"):
                raise
            log.info("not frozen (%s): %s", self.fn.__name__, err.__cause__ or err)
            self.frozen = None
            return self.fn(*args)
        if self.frozen.n_recordings > before:
            key = tuple(a for a in args if isinstance(a, int | str) or _names(a))
            self.recorded[key] = self.recorded.get(key, 0) + 1
            if self.recorded[key] > RERECORD_LIMIT:
                log.info("not frozen (%s): it records again on every call", self.fn.__name__)
                self.frozen = None
        return out


def _names(value) -> bool:
    """A tuple of strings (traverse keys): part of a frozen call's host arguments."""
    return isinstance(value, tuple) and all(isinstance(v, str) for v in value)


class _Group:
    """Views rendered together: one loaded scene, its parameters and, per free parameter, the
    traverse keys it sets (and emitter scales' configured values). Its `parts` are the scene's
    sensors, each with the views it renders: several views of perspective cameras through one
    `batch` sensor (side by side in one film), those of thin-lens or orthographic cameras one
    sensor each (`_UNTRAVERSED_SENSORS`: a frozen `batch` of them replayed wrong derivatives
    while other scenes were alive in the process, Dr.Jit 1.5 / Mitsuba 3.9.1; one sensor per
    view renders the same kernel for each, compiled once)."""

    def __init__(self, capture: Capture, views: list[int], material, free: list[Free], freeze):
        scene = scene_dict(capture.scene_of(views[0]), material, 0, 1)
        cameras = [capture.views[i].camera for i in views]
        bounds = bounding_sphere(capture.scene.geometry)
        sensors = [sensor_dict(c, 1, bounds) for c in cameras]
        if len(views) == 1:
            parts = [(0, views)]
        elif any(d["type"] != "perspective" for d in sensors):
            del scene["sensor"]
            # clip distances are host scalars, baked into the kernel: one range for all views
            # (each sensor's own compiled a kernel per view: the cup's first run 5 min 22 s)
            near = min(d["near_clip"] for d in sensors)
            far = max(d["far_clip"] for d in sensors)
            for d in sensors:
                d.update(near_clip=near, far_clip=far)
            scene.update({f"sensor_{k:04d}": d for k, d in enumerate(sensors)})
            parts = [(k, [v]) for k, v in enumerate(views)]
        else:
            scene["sensor"] = batch_sensor_dict(cameras, 1, bounds)
            parts = [(0, views)]
        self.views, self.scene = views, load_scene(scene)
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
        #: (sensor index, its views, its thin lenses' floats for `_rebuild_sensor`)
        self.parts = [(k, v, _sensor_floats(self.scene, k)) for k, v in parts]
        for k, _, floats in self.parts:
            # what a pass's first call makes or rebuilds (the film's storage, a thin lens's
            # members) made now: made inside it, it changed the next call's inputs, and Dr.Jit
            # recorded that call again (each pass, each sensor)
            self.scene.sensors()[k].film().prepare([])
            _rebuild_sensor(self.scene, k, floats)

        def wrap(fn):
            return _Frozen(fn, len(self.parts)) if freeze else fn

        # module functions, not bound methods: a Renderer holding its own bound methods is a
        # reference cycle, freed only by the cyclic collector, possibly inside a later recording
        self.primal, self.reverse = wrap(_primal), wrap(_reverse_pass)
        self.reverse_imaged = wrap(_reverse_pass_imaged)
        self.forward = wrap(_forward_pass)
        self.jacobian_primal, self.jacobian_column = wrap(_jacobian_primal), wrap(_jacobian_column)


class Renderer:
    """Loaded scenes of a capture's views with one material; parameters `free` are set from flat
    physical vectors. Scalars stay opaque (the plugins mark them), so changing values or the
    sample count between calls does not recompile kernels. All outputs are float32, views
    flattened and concatenated in the capture's order.

    Views that share the scene's lights and their size render from one scene: through one
    `batch` sensor (side by side in one film, one kernel per pass for all of them), or with
    thin-lens or orthographic cameras one sensor each (one kernel, launched per view); one scene
    per view would compile one kernel per view (the cup's reverse pass: ~15 s of LLVM each on 2
    cores). Views with their own lights (photometric stereo) get a scene each.

    With `freeze` (the default) primal renders, reverse passes and the Jacobian's forward passes
    are Dr.Jit frozen functions: recorded at the first call per spp, replayed after without
    re-tracing the path tracer in Python (measured on the Cycles sphere at 8 spp: 1.7x faster
    primal, 2.1x faster reverse pass; a Jacobian of two 48x36 views 4-6x faster). Thin-lens and
    orthographic cameras, which Mitsuba 3.9 does not declare to the recording, are rebuilt
    inside it (`_rebuild_sensor`); the cup's five thin-lens views of 64x56: an Adam step at 8
    spp 0.69-0.82 s frozen, 1.19 s re-traced. A function whose recording fails runs unfrozen
    from then on (`_Frozen`). A free texture is read by the `texels` plugin (`_with_texels`)."""

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
        material = _with_texels(material, free)
        # free the scenes of earlier fits in this process first: Python plugins' objects live in
        # reference cycles (and renders run with the collector off, `_no_gc`), and a frozen
        # render recorded while dead ones remain fails on their virtual calls ("validate(): The
        # frozen function included a virtual function call ..."), so every later fit ran
        # unfrozen: a sphere case after the DiLiGenT pot's fit 71 s, 16 s with this. Under the
        # render lock: never while another thread records (freeing a scene then aborts)
        with _ONE_AT_A_TIME:
            gc.collect()
        groups = [list(range(len(views)))] if batched else [[i] for i in range(len(views))]
        self.groups = [_Group(capture, g, material, free, freeze) for g in groups]
        self.scenes = [g.scene for g in self.groups]
        self.params = [g.params for g in self.groups]

    def _split(self, views: list[int], image) -> list[np.ndarray]:
        """A sensor's image (`views` side by side) as its views' flat images."""
        image = np.asarray(image, np.float32)[..., :3]
        w = self.shapes[views[0]][1]
        return [image[:, k * w : (k + 1) * w].ravel() for k in range(len(views))]

    def _join(self, views: list[int], flat_views: list[np.ndarray]) -> np.ndarray:
        """Views' flat images (cotangents) side by side as their sensor's image."""
        shapes = [self.shapes[v] for v in views]
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
                if f.shape and not grad:
                    _write_texels(params[key], chunk)
                    continue
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

    def _columns(self, group: _Group):
        """Each Jacobian column's tangents: every parameter gets one, zero but the column's own
        (one AD graph, one kernel for all columns: a tangent on one parameter alone is a new
        kernel, ~10 s of LLVM each for the cup)."""
        for f in self.free:
            for c in range(f.size):
                yield [
                    self._tangent(group, other, key, c if other is f else None)
                    for other, other_keys in zip(self.free, group.targets, strict=True)
                    for key in other_keys
                ]

    def _offsets(self) -> list[int]:
        return list(np.cumsum([0] + [int(np.prod(s)) for s in self.shapes]))

    @staticmethod
    def _seed(seed: int, g: int, sensor: int):
        """A sensor's seed: views rendered apart get independent samples. Opaque: a literal seed
        that changed made Dr.Jit record a frozen pass again (the cup's Jacobian: 2 s)."""
        value = mi.UInt32((int(seed) + 7919 * g + 104729 * sensor) % 2**32)
        dr.make_opaque(value)
        return value

    @_serialised
    def render(self, values: np.ndarray, seed: int, spp: int) -> np.ndarray:
        out = [None] * len(self.shapes)
        for g, group in enumerate(self.groups):
            self._set(group, values)
            for sensor, views, floats in group.parts:
                with _no_gc():
                    image = group.primal(
                        group.scene, self._seed(seed, g, sensor), spp, sensor, floats
                    )
                for v, part in zip(views, self._split(views, image), strict=True):
                    out[v] = part
        return np.concatenate(out)

    @_serialised
    def vjp(self, values: np.ndarray, seed: int, spp: int, cotangent: np.ndarray) -> np.ndarray:
        """Gradient of `<cotangent, render(values)>` with respect to `values`, from paths of their
        own (the seed plus `GRAD_SEED_OFFSET`)."""
        return self._reverse(values, seed + GRAD_SEED_OFFSET, spp, cotangent, False)[1]

    @property
    def imaged(self) -> bool:
        """Whether `render_vjp` is one pass (`imaged` integrators): else it is two."""
        return all(imaged(g.scene.integrator()) for g in self.groups)

    @_serialised
    def render_vjp(
        self, values: np.ndarray, seed: int, spp: int, cotangent: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """`render(values, seed, spp)` and the gradient of `<cotangent, render(values)>` from the
        same paths: one reverse pass whose primal pass is the image (`imaged`). The image and
        the gradient are correlated: their product's expectation is not the product of theirs,
        so `cotangent` must not depend on this image."""
        if not self.imaged:
            image = self.render(values, seed, spp)
            return image, self._reverse(values, seed, spp, cotangent, False)[1]
        return self._reverse(values, seed, spp, cotangent, True)

    def _reverse(self, values, seed: int, spp: int, cotangent, with_image: bool):
        """(the image with `with_image`, else None; the gradient of `<cotangent, render>`) from
        reverse passes at `seed`."""
        grad = np.zeros(self.n_params, np.float32)
        out = [None] * len(self.shapes)
        offsets = self._offsets()
        for g, group in enumerate(self.groups):
            self._set(group, values)
            keys = tuple(k for ks in group.targets for k in ks)
            for sensor, views, floats in group.parts:
                flat = [cotangent[offsets[v] : offsets[v + 1]] for v in views]
                grad_in = _owned(mi.TensorXf(self._join(views, flat)))
                seed_s = self._seed(seed, g, sensor)
                args = (group.scene, grad_in, seed_s, spp, keys, sensor, floats)
                with _no_gc():
                    if with_image:
                        image, grads = group.reverse_imaged(*args)
                        for v, part in zip(views, self._split(views, image), strict=True):
                            out[v] = part
                    else:
                        grads = group.reverse(*args)
                grads, i = iter(grads), 0
                for f, ks in zip(self.free, group.targets, strict=True):
                    for key in ks:
                        d = np.asarray(next(grads), np.float64)
                        if f.emitter:  # d/ds of base * s
                            bases = group.bases[key].reshape(-1)
                            grad[i] += float(np.sum(d.reshape(-1) * bases))
                        else:
                            grad[i : i + f.size] += np.ravel(d).astype(np.float32)
                    i += f.size
            self._drop_ad(group, values)
        return (np.concatenate(out) if with_image else None), grad

    def _drop_ad(self, group: _Group, values: np.ndarray) -> None:
        """Set the values again without derivatives after a pass that enabled them: unfrozen, a
        value the plugins derived from a differentiated one (a bitmap's mean) keeps its AD graph
        in the scene, and a later frozen pass of another Renderer in this process (a Ray worker's
        next fit) fails on that stale graph (`ad_traverse(): ... outside of the current
        dr.isolate_grad() scope`)."""
        self._set(group, values)

    @_serialised
    def jacobian(
        self, values: np.ndarray, seed: int, spp: int, jacobian_spp: int | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """(image, d image / d values): a forward-mode pass per parameter component, all from one
        primal pass (`_jacobian_primal`, `imaged` integrators; Mitsuba's `render_forward` renders
        the primal pass again for each).

        By default all with the image's seed and spp: the exact Jacobian of this seed's image (what
        LM needs to converge on a fixed objective, whose optimum is biased at low spp: the noise's
        own gradient enters). With `jacobian_spp` the Jacobian is rendered with a decorrelated seed
        at that spp: then `J^T r` is an unbiased gradient, and a cheap Jacobian preconditions an
        expensive, accurate residual."""
        j_seed, j_spp = (
            (seed, spp) if jacobian_spp is None else (seed + GRAD_SEED_OFFSET, jacobian_spp)
        )
        # one primal pass for the image and every column (`_jacobian_primal`) where the integrator
        # allows it, else a forward pass per column, each rendering its primal pass again
        shared = self.imaged
        image = None if shared and jacobian_spp is None else self.render(values, seed, spp)
        out = [None] * len(self.shapes)
        jac = np.zeros((self.size, self.n_params), np.float32)
        offsets = self._offsets()
        for g, group in enumerate(self.groups):
            self._set(group, values)
            keys = tuple(k for ks in group.targets for k in ks)
            seeds = [self._seed(j_seed, g, sensor) for sensor, _, _ in group.parts]
            states = []  # each sensor's primal radiance, kept for all columns
            for (sensor, views, floats), seed_s in zip(group.parts, seeds, strict=True):
                if shared:
                    with _no_gc():
                        primal, state = group.jacobian_primal(
                            group.scene, seed_s, j_spp, sensor, floats
                        )
                    states.append(state)
                    if image is None:
                        for v, part in zip(views, self._split(views, primal), strict=True):
                            out[v] = part
            for column, tangents in enumerate(self._columns(group)):
                for k, (sensor, views, floats) in enumerate(group.parts):
                    with _no_gc():
                        if shared:
                            derivative = group.jacobian_column(
                                group.scene, tangents, states[k], seeds[k], j_spp, keys, sensor,
                                floats,
                            )  # fmt: skip
                        else:
                            derivative = group.forward(
                                group.scene, tangents, seeds[k], j_spp, keys, sensor, floats
                            )
                    for v, part in zip(views, self._split(views, derivative), strict=True):
                        jac[offsets[v] : offsets[v + 1], column] = part
            self._drop_ad(group, values)
        return (np.concatenate(out) if image is None else image), jac
