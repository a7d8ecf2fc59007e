"""Recovery over the parameter range: synthetic targets rendered by layerfit, fitted back from one
start with a schedule, scored against the truth and the reported standard deviations.

Each case is a glaze (pigment, Beckmann alpha, ior) on a shape seen by three cameras in a small
studio (two rectangle lights, a dim environment) scaled to the shape's bounding sphere, so every
shape is framed and lit alike. The target is a high-spp render (no model mismatch, no photographic
noise: what is left is the fit's own error). `layerfit bench --only recovery` prints the
calibration table (error / sigma per case); tests run a fast subset.
"""

from __future__ import annotations

import math
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from captures.capture import Capture, View
from captures.geometry import CupShape
from captures.scene import Camera, Cup, ObjFile, RectLight, Scene, Sphere, bounding_sphere

#: The accuracy targets: alpha within 5 % relative, ior within 0.03, pigment within 0.02 per
#: channel, and each error within 3 reported standard deviations.
ALPHA_REL, IOR_ABS, PIGMENT_ABS, MAX_SIGMAS = 0.05, 0.03, 0.02, 3.0

#: Samples per pixel of a case's target, at least (`target_spp`).
TARGET_SPP = 256
#: A target's own noise may move alpha's optimum by at most this share of alpha (its sd over
#: targets, `data_limit`): a third of the target, so that a miss is the fit's, not the target's.
ALLOWANCE = ALPHA_REL / 3
#: The most samples per pixel a target gets (three 160x120 views of a glossy torus: the
#: allowance there needs more; the table prints what it holds).
MAX_TARGET_SPP = 16384

#: The fits' start (the configs' and the tutorial loop's): grey, rough, low ior.
START = {"glaze.pigment": [0.5, 0.5, 0.5], "glaze.roughness": 0.2, "glaze.ior": 1.3}
KEYS = tuple(START)
#: A case's values unless it varies them: the default job's blue glaze.
BASE = {"glaze.pigment": (0.1, 0.22, 0.55), "glaze.roughness": 0.1, "glaze.ior": 1.5}

#: The sweep's shapes: the analytic sphere and a torus mesh (curved both ways, so every view
#: sees highlights; saddle regions). The procedural cup is available too (`--shapes cup`): its
#: cylindrical walls show these studio lights' highlights to none of the three cameras at low
#: alpha, which the sweep reports as undetermined (BENCHMARKS).
SHAPES = ("sphere", "torus", "cup")
DEFAULT_SHAPES = ("sphere", "torus")
#: Every truth strictly inside alpha's bounds [0.002, 1].
ALPHAS = (0.005, 0.01, 0.02, 0.05, 0.1, 0.3, 0.6, 0.9)
IORS = (1.05, 1.3, 1.5, 2.0, 2.8)
PIGMENTS = {
    "dark": (0.02, 0.02, 0.025),
    "white": (0.9, 0.9, 0.9),
    "saturated": (0.8, 0.08, 0.02),
}


@dataclass(frozen=True)
class Case:
    """One target: a shape and the glaze's true values."""

    shape: str
    pigment: tuple[float, float, float] = BASE["glaze.pigment"]
    roughness: float = BASE["glaze.roughness"]
    ior: float = BASE["glaze.ior"]
    label: str = "base"

    @property
    def name(self) -> str:
        return f"{self.shape}: {self.label}"

    def truth(self) -> dict:
        return {
            "glaze.pigment": list(self.pigment),
            "glaze.roughness": self.roughness,
            "glaze.ior": self.ior,
        }


def sweep(shapes=DEFAULT_SHAPES) -> list[Case]:
    """The full sweep: each shape with alpha, then ior, then the pigment varied alone."""
    cases = []
    for shape in shapes:
        cases += [Case(shape, roughness=a, label=f"alpha {a:g}") for a in ALPHAS]
        cases += [Case(shape, ior=n, label=f"ior {n:g}") for n in IORS]
        cases += [Case(shape, pigment=p, label=f"{name} pigment") for name, p in PIGMENTS.items()]
    return cases


def geometry(shape: str):
    if shape == "sphere":
        return Sphere()
    if shape == "torus":
        return ObjFile(torus_obj())
    if shape == "cup":
        return Cup(CupShape(segments=64))
    raise ValueError(f"shape {shape!r}; choose one of {', '.join(SHAPES)}")


def torus_obj(major: float = 1.0, minor: float = 0.4, segments: int = 96) -> Path:
    """A torus mesh (axis tilted 30 degrees toward the front camera, so its hole shows) with
    UVs and normals, written once to the temporary folder (atomically) and reused."""
    from captures.files import write_text

    path = Path(tempfile.gettempdir()) / f"layerfit-torus-{major}-{minor}-{segments}.obj"
    if path.exists():
        return path
    n_u, n_v = segments, segments // 2
    u, v = np.meshgrid(np.arange(n_u + 1) / n_u, np.arange(n_v + 1) / n_v, indexing="ij")
    phi, theta = 2 * np.pi * u, 2 * np.pi * v
    normal = np.stack([np.cos(theta) * np.cos(phi), np.cos(theta) * np.sin(phi), np.sin(theta)])
    ring = np.stack([np.cos(phi), np.sin(phi), np.zeros_like(phi)])
    position = major * ring + minor * normal
    tilt = np.radians(30.0)
    rotate = np.array(
        [[1, 0, 0], [0, np.cos(tilt), -np.sin(tilt)], [0, np.sin(tilt), np.cos(tilt)]]
    )
    position = np.einsum("ij,jab->abi", rotate, position).reshape(-1, 3)
    normal = np.einsum("ij,jab->abi", rotate, normal).reshape(-1, 3)
    uv = np.stack([u, v], axis=-1).reshape(-1, 2)
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in position]
    lines += [f"vt {a:.6f} {b:.6f}" for a, b in uv]
    lines += [f"vn {x:.6f} {y:.6f} {z:.6f}" for x, y, z in normal]
    for i in range(n_u):
        for j in range(n_v):
            a, b = i * (n_v + 1) + j + 1, (i + 1) * (n_v + 1) + j + 1
            quad = (a, b, b + 1, a + 1)
            for tri in ((quad[0], quad[1], quad[2]), (quad[0], quad[2], quad[3])):
                lines.append("f " + " ".join(f"{k}/{k}/{k}" for k in tri))
    write_text(path, "\n".join(lines) + "\n")
    return path


def studio(shape: str, width: int, height: int) -> Scene:
    """Three cameras (front, right, upper left) and two rectangle lights (a warm key upper right,
    a cool fill left) around the shape's bounding sphere, at five radii (the glazed sphere's
    studio, scaled). Light radiance is scale-free (the lights subtend the same solid angles)."""
    geo = geometry(shape)
    center, radius = bounding_sphere(geo)

    def at(offset) -> tuple[float, float, float]:
        return tuple(float(c) for c in center + radius * np.asarray(offset, float))

    cameras = tuple(
        Camera(at(o), tuple(map(float, center)), (0.0, 0.0, 1.0), 39.6, width, height)
        for o in ((0.0, -5.0, 1.2), (3.5, -3.5, 0.8), (-2.5, -4.0, 2.5))
    )
    lights = (
        RectLight(
            at((3.0, -2.5, 3.0)),
            (0.6402, 0.7682, 0.0),
            (-0.4680, 0.3900, 0.7930),
            (1.2 * radius, 0.8 * radius),
            (-0.6092, 0.5077, -0.6092),
            (200.0, 183.0, 163.0),
        ),
        RectLight(
            at((-3.5, -1.0, 1.5)),
            (0.2747, -0.9615, 0.0),
            (0.3663, 0.1047, 0.9246),
            (0.6 * radius, 0.6 * radius),
            (0.8890, 0.2540, -0.3810),
            (106.0, 117.0, 133.0),
        ),
    )
    return Scene(geo, cameras, lights, environment=(0.05, 0.05, 0.06), max_depth=8)


def glaze(values: dict, fresnel: str = "schlick"):
    """A glaze `Material` with `values` (design keys)."""
    from .material import build_material

    table = {
        "type": "glaze",
        "coupling": "paper",
        "fresnel": fresnel,
        "pigment": list(values["glaze.pigment"]),
        "roughness": float(values["glaze.roughness"]),
        "ior": float(values["glaze.ior"]),
    }
    return build_material(table, "<recovery>")


def capture(case: Case, width: int = 96, height: int = 72, spp: int = TARGET_SPP, seed: int = 0):
    """The case's synthetic capture: each view rendered at `spp` (truth in `capture.truth`)."""

    from .render import load_scene, render, scene_dict

    scene = studio(case.shape, width, height)
    material = glaze(case.truth())
    views = []
    for i, camera in enumerate(scene.cameras):
        loaded = load_scene(scene_dict(scene, material, i, spp))
        image = render(loaded, spp, seed + 1000 * i)
        views.append(View(f"view_{i:02d}", image, np.ones((height, width), np.float32), camera))
    return Capture(scene, views, truth=case.truth())


def fit_label(case: Case, seed: int) -> str:
    """A fit's name: its case's, and its seed where it is not 0 (the sweep's own)."""
    return case.name + (f", seed {seed}" if seed else "")


@dataclass
class Outcome:
    """A case's fitted values, standard deviations and wall time; its target's samples per
    pixel and what they allow alpha (`target_spp`), where known."""

    case: Case
    values: dict
    std: dict
    seconds: float
    errors: dict = field(init=False)
    sigmas: dict = field(init=False)
    target_spp: int | None = None
    allowance: float | None = None
    seed: int = 0  # the fit's

    @property
    def label(self) -> str:
        return fit_label(self.case, self.seed)

    def __post_init__(self):
        truth = self.case.truth()
        self.errors = {k: np.subtract(self.values[k], truth[k]).tolist() for k in KEYS}
        self.sigmas = {
            k: (np.abs(self.errors[k]) / np.maximum(np.asarray(self.std[k], float), 1e-12)).tolist()
            for k in KEYS
        }

    def within_targets(self) -> dict[str, bool]:
        """Whether each parameter is within its target (alpha relative, the others absolute)."""
        alpha = abs(self.errors["glaze.roughness"]) / self.case.roughness
        return {
            "glaze.roughness": alpha <= ALPHA_REL,
            "glaze.ior": abs(self.errors["glaze.ior"]) <= IOR_ABS,
            "glaze.pigment": bool(np.max(np.abs(self.errors["glaze.pigment"])) <= PIGMENT_ABS),
        }

    def within_sigmas(self) -> dict[str, bool]:
        return {k: bool(np.max(self.sigmas[k]) <= MAX_SIGMAS) for k in KEYS}

    def passed(self) -> bool:
        return all(self.within_targets().values()) and all(self.within_sigmas().values())

    @classmethod
    def from_dict(cls, case: Case, saved: dict) -> Outcome:
        """An outcome saved by `as_dict` (an undetermined sd, saved as null, infinite again)."""
        std = {k: _map(v, lambda x: math.inf if x is None else x) for k, v in saved["std"].items()}
        allowance = saved.get("allowance")  # absent: a target given; null: undetermined
        if "allowance" in saved and allowance is None:
            allowance = math.inf
        spp = saved.get("target_spp")
        return cls(
            case, saved["values"], std, saved["seconds"], spp, allowance, saved.get("seed", 0)
        )

    def as_dict(self) -> dict:
        """The outcome as strict JSON values (an undetermined, infinite sd as null)."""
        std = {k: strict(v) for k, v in self.std.items()}
        return {
            "case": self.case.name,
            "seed": self.seed,
            "truth": self.case.truth(),
            "values": self.values,
            "std": std,
            "errors": self.errors,
            "sigmas": self.sigmas,
            "seconds": self.seconds,
            **(
                {"target_spp": self.target_spp, "allowance": strict(self.allowance)}
                if self.target_spp is not None and self.allowance is not None
                else {}
            ),
            "within_targets": self.within_targets(),
            "within_sigmas": self.within_sigmas(),
            "passed": self.passed(),
        }


def case_target(case: Case, width: int, height: int, spp: int = TARGET_SPP) -> Capture:
    """The case's target, rendered with seeds of its own: with shared ones, every case's fit
    inherits the same noise realisation (the sweep's ior errors all came out positive)."""
    return capture(case, width, height, spp, seed=zlib.crc32(case.name.encode()) % 100_000)


#: `data_limit`'s Jacobian samples and noise pairs when it picks a target's samples (at 1024 and
#: 8 it took 45 s a case at 160x120).
TARGET_LIMIT_SPP, TARGET_LIMIT_PAIRS = 128, 4


def target_spp(case: Case, width: int, height: int) -> tuple[int, float]:
    """The samples per pixel of the case's clean target and what it allows alpha (its sd over
    such targets, `data_limit`, as a share of alpha; infinite where undetermined): `TARGET_SPP`
    doubled until that share is within `ALLOWANCE`, at most `MAX_TARGET_SPP` (the sd falls as
    one over the root of the samples). From a cheaper `data_limit` than its default
    (`TARGET_LIMIT_SPP`, `TARGET_LIMIT_PAIRS`): it only picks a power of two."""
    limit = data_limit(case, width, height, TARGET_LIMIT_SPP, pairs=TARGET_LIMIT_PAIRS)
    sd = limit["glaze.roughness"] / case.roughness
    spp = TARGET_SPP
    while spp < MAX_TARGET_SPP and not sd * math.sqrt(TARGET_SPP / spp) <= ALLOWANCE:
        spp *= 2
    return spp, sd * math.sqrt(TARGET_SPP / spp)


def _map(value, f):
    """`f` of a number, or of each number of a list."""
    return [f(x) for x in value] if isinstance(value, list) else f(value)


def strict(value):
    """A number, or each of a list, as strict JSON: an infinite one (undetermined) as null."""
    return _map(value, lambda x: x if math.isfinite(x) else None)


def recover(
    case: Case,
    schedule=None,
    width: int = 96,
    height: int = 72,
    seed: int = 0,
    target: Capture | None = None,
    clean: tuple[Capture, int, float] | None = None,
) -> Outcome:
    """Fit `case` back from `START` with `schedule` (the default one unless given) and `seed`,
    against `target`, else its clean target (`clean`, as `clean_target` gives it: rendered once
    for several seeds; default: rendered here)."""
    from .material import resolve
    from .solvers import DEFAULT_SCHEDULE, Problem, run_schedule

    spp = allowance = None
    if target is None:
        target, spp, allowance = clean or clean_target(case, width, height)
    material = glaze(START)
    problem = Problem(target, material, resolve(material, list(KEYS)))
    began = time.perf_counter()
    result = run_schedule(problem, START, schedule or DEFAULT_SCHEDULE, seed)
    seconds = time.perf_counter() - began
    values = {k: result.values[k] for k in KEYS}
    return Outcome(case, values, dict(result.std), seconds, spp, allowance, seed)


def clean_target(case: Case, width: int, height: int) -> tuple[Capture, int, float]:
    """The case's clean target, its samples per pixel and what they allow alpha
    (`target_spp`)."""
    spp, allowance = target_spp(case, width, height)
    return case_target(case, width, height, spp), spp, allowance


#: Samples per pixel of each of `data_limit`'s two Jacobian renders, and its pairs of renders
#: at the target's samples whose differences give a target's noise (Monte Carlo noise is heavy
#: tailed: one pair's estimate of a 48x36 sphere's pigment sd varied 1.5x with its seeds).
LIMIT_SPP, NOISE_PAIRS = 1024, 8


def data_limit(
    case: Case,
    width: int = 96,
    height: int = 72,
    spp: int = LIMIT_SPP,
    target_spp: int = TARGET_SPP,
    seed: int = 0,
    pairs: int = NOISE_PAIRS,
) -> dict:
    """What the case's targets allow: each parameter's standard deviation, over targets rendered
    at `target_spp`, of the least-squares optimum against one (`H^-1 J^T e`, e a target's noise),
    infinite where not determined. No fit: its own Monte Carlo error comes on top, whatever its
    schedule.

    J from two independent Jacobian renders of `spp` at the truth (their cross products: a
    Jacobian's own noise would add to `J^T J` and to the meat), a target's per-pixel noise from
    the differences of `NOISE_PAIRS` pairs of renders at `target_spp` (a pixel's channels share
    their paths, so the meat sums each pixel's channels first and keeps its positive part, as
    the fit's uncertainty does: `pixel_meat`)."""
    from .material import as_dict, resolve
    from .solvers import Problem
    from .solvers.uncertainty import (
        CROSS_SEED_OFFSET,
        cross_product,
        inverse_determined,
        pixel_meat,
    )

    material = glaze(START)
    problem = Problem(case_target(case, width, height), material, resolve(material, list(KEYS)))
    _, sqrt_w = problem.target()
    renderer = problem.renderer()
    truth = case.truth()
    x = np.concatenate([np.ravel(truth[k]) for k in KEYS]).astype(np.float32)
    j1, j2 = (
        sqrt_w[:, None] * renderer.jacobian(x, s, spp)[1] for s in (seed, seed + CROSS_SEED_OFFSET)
    )

    def target_noise(k: int) -> np.ndarray:  # a target's noise: two renders' difference / sqrt(2)
        a, b = (renderer.render(x, seed + (2 * k + i) * 0x51ED, target_spp) for i in (1, 2))
        return sqrt_w * (a - b) / np.sqrt(2.0)

    # every pair's terms stacked: the meat is their mean, its positive part taken once
    noises = [target_noise(k) for k in range(pairs)]
    meat = pixel_meat(*(np.concatenate([j * e[:, None] for e in noises]) for j in (j1, j2)))
    meat /= pairs
    bread, undetermined = inverse_determined(cross_product(j1, j2))
    std = np.sqrt(np.clip(np.diag(bread @ meat @ bread), 0.0, None))
    std[undetermined] = np.inf
    return as_dict(problem.free, std)


def calibration_rows(outcomes: list[Outcome]) -> list[list[str]]:
    """Per case: each parameter's error and error/sigma, a mark where a target is missed, and
    the target's samples per pixel with what they allow alpha."""
    rows = []
    for o in outcomes:
        targets, sigmas = o.within_targets(), o.within_sigmas()
        alpha = o.errors["glaze.roughness"] / o.case.roughness
        pig = int(np.argmax(np.abs(o.errors["glaze.pigment"])))

        def mark(key, targets=targets, sigmas=sigmas):
            return "" if targets[key] and sigmas[key] else " ✗"

        def sd(key, index=None, o=o):
            std = np.ravel(o.std[key])[0 if index is None else index]
            ratio = np.ravel(o.sigmas[key])[0 if index is None else index]
            return "undetermined" if not np.isfinite(std) else f"{ratio:.1f} sd"

        rows.append(
            [
                o.label,
                f"{100 * alpha:+.1f} % ({sd('glaze.roughness')})" + mark("glaze.roughness"),
                f"{o.errors['glaze.ior']:+.4f} ({sd('glaze.ior')})" + mark("glaze.ior"),
                f"{o.errors['glaze.pigment'][pig]:+.4f} ({sd('glaze.pigment', pig)})"
                + mark("glaze.pigment"),
                f"{o.seconds:.0f}",
                _target(o),
                "yes" if o.passed() else "no",
            ]
        )
    return rows


def _target(outcome: Outcome) -> str:
    """`spp (allows alpha x %)`, or `-` for an outcome of a target given."""
    if outcome.target_spp is None:
        return "-"
    allowance = outcome.allowance
    allows = (
        "undetermined"
        if allowance is None or not math.isfinite(allowance)
        else (f"{100 * allowance:.1f} %")
    )
    return f"{outcome.target_spp} ({allows})"
