"""What the object is made of: Mitsuba plugins written in Python, and their parameters.

Importing this package changes nothing; `register()` adds the plugins to the current Mitsuba
variant (the caller chooses the variant; this package never sets one).
"""

from .params import (
    EMITTER_PARAMS,
    FBM,
    GLAZE,
    GLAZE_PARAMS,
    LAYER_PLUGINS,
    LAYERED,
    OREN_NAYAR,
    OREN_NAYAR_PARAMS,
    ChoiceOption,
    IntOption,
    ParamSpec,
    PluginDecl,
)

__all__ = [
    "EMITTER_PARAMS",
    "FBM",
    "GLAZE",
    "GLAZE_PARAMS",
    "LAYERED",
    "LAYER_PLUGINS",
    "OREN_NAYAR",
    "OREN_NAYAR_PARAMS",
    "ChoiceOption",
    "IntOption",
    "ParamSpec",
    "PluginDecl",
    "register",
]


def register() -> None:
    """Register `oren_nayar`, `glaze`, `layered` (BSDFs), `fbm` and `texels` (textures) with the
    current Mitsuba variant."""
    import mitsuba as mi

    if mi.variant() is None:
        raise RuntimeError("materials.register(): set a Mitsuba variant first (mi.set_variant)")
    from .fbm import FbmMask
    from .glaze import Glaze
    from .layered import Layered
    from .oren_nayar import OrenNayar
    from .texels import Texels

    mi.register_bsdf("oren_nayar", OrenNayar)
    mi.register_bsdf("glaze", Glaze)
    mi.register_bsdf("layered", Layered)
    mi.register_texture("fbm", FbmMask)
    mi.register_texture("texels", Texels)
