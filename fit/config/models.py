"""The config models and their loaders (see the package's docstring for the files)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from captures import Scene, parse_scene
from captures.model import (
    FieldError,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    StrictModel,
    expect_kind,
    parse_model,
)

from ..errors import ConfigError
from ..limits import MAX_SEED, MAX_SPP, QUALITIES
from ..material import Material, load_material, read_toml
from ..material.textures import MAX_TEXELS, with_free_textures
from ..solvers.schedule import (
    DEFAULT_SCHEDULE,
    Phase,
    at_quality,
    default_schedule,
)


class RenderSettings(StrictModel):
    spp: Annotated[PositiveInt, Field(le=MAX_SPP)] = 64
    """Samples per pixel of each view (at most 2^20: `fit.limits.MAX_SPP`)."""


class _RenderFile(StrictModel):
    scene: dict[str, Any]
    """The scene: geometry, cameras, lights, environment (captures/schema.py)."""
    material: dict[str, Any] | str
    """The material table, or the name of a preset file (relative to the config)."""
    render: RenderSettings = RenderSettings()
    """How to render."""


#: `[fit.textures]`: a texture the size of the first photograph at `fit.downscale`.
PHOTO_SIZE = "photo"


class FitSettings(StrictModel):
    free: list[str] = Field(min_length=1)
    """The parameter keys the fit moves, e.g. ["glaze.roughness", "lime.mask.threshold"]."""
    seed: Annotated[NonNegativeInt, Field(le=MAX_SEED)] = 0
    """Seed of the renders (phase k uses seed + k), at most 2^32 - 1 (the renders' seeds are
    32-bit; the seeds derived from it wrap)."""
    gains: bool | Literal["exposure"] = False
    """A free gain per view, their geometric mean 1 (the declared exposures right on average):
    true, an RGB gain (unknown exposure and white balance); "exposure", one grey gain (one
    camera, its white balance fixed)."""

    @field_validator("free")
    @classmethod
    def _unique(cls, value):
        twice = sorted({k for k in value if value.count(k) > 1})
        if twice:
            raise ValueError(f"lists {', '.join(twice)} more than once; list each key once")
        return value

    @model_validator(mode="after")
    def _loss_scale_for_a_robust_loss(self):
        if self.loss_scale is not None and self.loss == "l2":  # it had no effect, silently
            raise FieldError(
                "loss_scale", 'applies to loss = "huber" or "cauchy"; remove it, or set loss'
            )
        return self

    @model_validator(mode="before")
    @classmethod
    def _texture_sizes(cls, data):
        textures = data.get("textures") if isinstance(data, dict) else None
        if not isinstance(textures, dict):
            return data  # pydantic says what else is wrong
        for key, size in textures.items():
            if isinstance(size, str) and size != PHOTO_SIZE:
                raise FieldError(
                    f"textures.{key}",
                    f'got {size!r}; give [width, height] in texels or "{PHOTO_SIZE}" (the first '
                    "photograph's size at fit.downscale)",
                )
        return data

    @model_validator(mode="after")
    def _textures_are_free(self):
        for key, size in self.textures.items():
            if key not in self.free:
                raise FieldError(f"textures.{key}", f"is not in fit.free; add {key!r} to it")
            if size != PHOTO_SIZE and size[0] * size[1] > MAX_TEXELS:
                raise FieldError(
                    f"textures.{key}",
                    f"{size[0]} x {size[1]} texels is more than {MAX_TEXELS}; give fewer",
                )
        return self

    @model_validator(mode="after")
    def _default_phases(self):
        if "phases" not in self.model_fields_set:
            scalars = any(k not in self.textures for k in self.free)
            phases = default_schedule(self.free, bool(self.textures), scalars)
            object.__setattr__(self, "phases", list(phases))
        return self

    @field_validator("gains", mode="before")
    @classmethod
    def _gains(cls, value):
        if value is True or value is False or value == "exposure":
            return value
        raise ValueError(f'got {value!r}; should be true, false or "exposure"')

    textures: dict[str, tuple[PositiveInt, PositiveInt] | Literal["photo"]] = Field(
        default_factory=dict
    )
    """Parameters fitted as textures: key = [width, height] in texels, or "photo": the first
    photograph's size at `downscale` (a texel per pixel where UVs are the image's coordinates,
    a normal map's height field); colours (glaze.pigment, clay.reflectance) and masks' textures
    (<layer>.mask.texture), each also in `free`, starting from the material's value
    (fit/material/textures.py)."""
    loss: Literal["l2", "huber", "cauchy"] = "l2"
    """How a pixel's difference counts: l2, or robust huber / cauchy (biased under noise)."""
    loss_scale: PositiveFloat | None = None
    """Robust losses: differences beyond this count less (default: 0.1 x the photos' mean)."""
    uncertainty_spp: Annotated[PositiveInt, Field(le=MAX_SPP)] = 64
    """Samples per pixel of the final Jacobian render that gives the uncertainty."""
    downscale: PositiveInt = 1
    """Area-average the photos by this factor before anything (the cameras follow)."""
    holdout: NonNegativeInt = 0
    """Views kept out of the fit and only scored (spread over the views, never the first)."""
    phases: list[Phase] = Field(default_factory=lambda: list(DEFAULT_SCHEDULE), min_length=1)
    """The schedule: solver phases run in turn (absent: the default schedule, its first Adam
    steps holding the mask thresholds when any is free)."""
    quality: Literal[QUALITIES] = "default"
    """Trade time for accuracy: draft halves every phase's steps (and step limits), fits the
    full-resolution phases at half resolution (where the views keep 48 pixels a side), halves
    the samples of every phase but the last (for a material of one layer) and averages to a 5 %
    Monte Carlo sd, best doubles the steps (`schedule.at_quality`)."""
    starts: PositiveInt = 1
    """Multi-start: run the schedule from this many starts (Ray workers), keep the best."""
    start_spread: PositiveFloat = 1.5
    """Multi-start: standard deviation of the other starts around the configured one, in the
    solvers' unconstrained units (sigmoid: logits)."""
    starts_spp: Annotated[PositiveInt, Field(le=MAX_SPP)] = 256  # at most 2^20, as every spp
    """Multi-start: samples per pixel of the common loss that picks the best start."""


class _FitFile(StrictModel):
    capture: str
    """The capture: a folder with capture.toml, a peer scene.json or a DiLiGenT folder."""
    material: dict[str, Any] | str
    """The starting material: a table, or the name of a preset file (relative to the config)."""
    fit: FitSettings
    """What is free and how to solve."""


@dataclass(frozen=True)
class RenderConfig:
    """A loaded render config: the scene, the built material and the sample count."""

    path: Path
    scene: Scene
    material: Material
    spp: int


@dataclass(frozen=True)
class FitConfig:
    """A loaded fit config: the capture's path, the built starting material and the settings."""

    path: Path
    capture: Path
    material: Material
    settings: FitSettings

    @property
    def phases(self) -> list[Phase]:
        """The schedule's phases at the settings' quality preset, the views' size unknown (a
        draft halves every full-resolution phase's; a fit's own: `phases_for`)."""
        return list(at_quality(self.settings.phases, self.settings.quality, layered=self.layered))

    def phases_for(self, side: int) -> list[Phase]:
        """The schedule's phases at the quality preset for fitted views whose smallest side is
        `side` pixels at full resolution (`schedule.DRAFT_MIN_SIDE`)."""
        return list(
            at_quality(self.settings.phases, self.settings.quality, side, layered=self.layered)
        )

    @property
    def layered(self) -> bool:
        """Whether the material stacks more than one layer (`schedule.at_quality`)."""
        return len(self.material.layers) > 1

    def __getattr__(self, name):  # cfg.free, cfg.seed, ...: the [fit] settings
        if name in FitSettings.model_fields:
            return getattr(self.settings, name)
        raise AttributeError(name)


def config_identity(cfg: FitConfig) -> dict:
    """What a fit's config asks for (JSON values): its [fit] settings, capture and starting
    material. A batch skips a finished fit only while its config still asks for the same
    (`fit.batch.runner.finished`): an edited config runs again."""
    identity = {
        "settings": cfg.settings.model_dump(mode="json"),
        "capture": str(Path(cfg.capture).resolve()),
        "starting material": cfg.material.table(),
    }
    return json.loads(json.dumps(identity, default=str))


def load_render_config(path: str | Path) -> RenderConfig:
    """A render config from its file; a one-line `InputError` naming the file and key."""
    path = Path(path)
    doc = parse_model(_RenderFile, read_toml(path), path)
    material = load_material(doc.material, path)
    return RenderConfig(path, parse_scene(doc.scene, path), material, doc.render.spp)


def photo_size(capture: Path, downscale: int, name: str) -> tuple[int, int]:
    """(width, height) of a capture's first photograph area-averaged by `downscale` (named
    `name` in an error)."""
    from captures import open_capture

    camera = open_capture(capture, downscale, name).views[0].camera
    return camera.width, camera.height


def load_fit_config(
    path: str | Path, capture: Path | None = None, seed: int | None = None
) -> FitConfig:
    """A fit config from its file, its capture and seed replaced when given (a batch's); a
    one-line `InputError` naming the file and key."""
    path = Path(path)
    table = read_toml(path)
    expect_kind(
        table,
        path,
        "a fit config",
        "a fit config names its capture, a [material] and a [fit] table (configs/cup-fit.toml "
        "is one)",
        ConfigError,
    )
    doc = parse_model(_FitFile, table, path)
    if capture is None:
        capture = (path.parent / doc.capture).resolve()
        if not doc.capture.strip():
            raise ConfigError(
                f"{path}: capture = {doc.capture!r} is empty; give the capture's folder (holding "
                "capture.toml), a peer scene.json or a DiLiGenT folder, relative to the config"
            )
        if capture == path.resolve():
            raise ConfigError(
                f"{path}: capture = {doc.capture!r} is this fit config; give the capture's folder "
                "(holding capture.toml), a peer scene.json or a DiLiGenT folder"
            )
        if not capture.exists():
            raise ConfigError(
                f"{path}: capture = {doc.capture!r} does not exist (relative to {path.parent}); "
                "check the path"
            )
    material = load_material(doc.material, path)
    sizes = dict(doc.fit.textures)
    if PHOTO_SIZE in sizes.values():
        photo = photo_size(Path(capture), doc.fit.downscale, f"{path}: fit.downscale")
        for key, size in sizes.items():
            if size != PHOTO_SIZE:
                continue
            if photo[0] * photo[1] > MAX_TEXELS:
                raise ConfigError(
                    f'{path}: fit.textures.{key} = "photo": the first photograph at downscale '
                    f"{doc.fit.downscale} is {photo[0]} x {photo[1]}, more than {MAX_TEXELS} "
                    "texels; raise fit.downscale or give [width, height]"
                )
            sizes[key] = photo
    try:
        material = with_free_textures(material, sizes)
    except KeyError as err:
        raise ConfigError(f"{path}: fit.textures.{err.args[0]}") from None
    settings = doc.fit if seed is None else doc.fit.model_copy(update={"seed": seed})
    textures = [k for k in settings.free if k in material.texture_files()]
    if textures and "phases" not in settings.model_fields_set:  # a texture file's texels free
        scalars = any(k not in textures for k in settings.free)
        settings = settings.model_copy()  # still the default schedule: not a field set
        object.__setattr__(settings, "phases", list(default_schedule(settings.free, True, scalars)))
    return FitConfig(path, Path(capture), material, settings)
