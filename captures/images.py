"""Image files in and out through OpenImageIO; linear float32 (H, W, 3) arrays in memory."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from .errors import CaptureError
from .files import atomic_path, not_utf8, require_utf8

log = logging.getLogger(__name__)
ENCODINGS = ("linear", "srgb", "raw")
#: The largest half float: float images clip there (a value this high is saturated).
HALF_MAX = 65504.0


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear Rec.709 -> sRGB-encoded values in [0, 1] (clipped)."""
    x = np.clip(linear, 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """sRGB-encoded values in [0, 1] -> linear."""
    x = np.asarray(encoded, dtype=np.float32)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)


def read_image(
    path: str | Path, channels: tuple[int, int] | None = None, part: int = 0
) -> np.ndarray:
    """Pixels as float32 (H, W, C) exactly as stored (no colour decoding): all channels, or
    those from `channels[0]` up to `channels[1]` (a multi-layer file's passes left unread), of
    the file's `part` (a multi-part EXR's; `image_part`), over its display window."""
    path = Path(path)
    require_utf8(path, CaptureError)
    if not path.exists():
        raise CaptureError(f"{path}: no such image file; check the path")
    if path.is_dir():
        raise CaptureError(f"{path}: is a folder, not an image; give an image file")
    pixels, problem = _decode(path, channels, part)
    if problem is not None:
        raise CaptureError(f"{path}: {problem}")
    return pixels


def _first_line(error: str) -> str:
    """OpenImageIO's error text, first line (libpng and others repeat themselves below)."""
    lines = [line.strip() for line in error.strip().splitlines() if line.strip()]
    return lines[0] if lines else "no reason given"


@contextlib.contextmanager
def _c_stderr_silenced():
    """Keep C libraries from writing to the process's stderr (libpng prints each error there
    too; OpenImageIO hands it back, and it is reported once, in the error line)."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):  # no real stderr (e.g. captured): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _decode(
    path: Path, channels: tuple[int, int] | None = None, part: int = 0
) -> tuple[np.ndarray | None, str | None]:
    """The pixels as float32 (H, W, C) of the file's `part` over its display window (of
    `channels`, a range, where given), or why they cannot be read (one line)."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # colours as stored, not times alpha
    with _c_stderr_silenced():
        buf = oiio.ImageBuf(str(path), part, 0, config)
        opened = not buf.has_error
        pixels, cropped = None, None
        if opened:
            cropped = window_problem(buf.roi, buf.roi_full)
            roi = buf.roi_full  # an overscan's pixels beyond the frame left out
            if channels is None:
                channels = (roi.chbegin, roi.chend)
            roi = oiio.ROI(roi.xbegin, roi.xend, roi.ybegin, roi.yend, 0, 1, *channels)
            if cropped is None:
                pixels = buf.get_pixels(oiio.FLOAT, roi)
    if not opened:
        oiio.geterror()  # the same error, pending globally: cleared
        return None, f"cannot read image ({_first_line(buf.geterror())}); convert it"
    if cropped is not None:
        return None, cropped
    if pixels is None or buf.has_error:
        oiio.geterror()
        return None, (
            f"cannot decode its pixels ({_first_line(buf.geterror())}): the file is truncated "
            "or corrupt; copy or export it again"
        )
    return np.asarray(pixels, dtype=np.float32), None


def window_problem(data, display) -> str | None:
    """Why an image whose pixels (its data window, an OpenImageIO ROI) do not cover its frame
    (its display window) is refused, None where they do. A render region or an autocropped EXR
    stores only part of the frame: the rest is not black, it was not rendered (it was reported
    as an image of another size than the camera's). An overscan, pixels beyond the frame, is
    read over the frame."""
    if (
        data.xbegin <= display.xbegin
        and data.ybegin <= display.ybegin
        and data.xend >= display.xend
        and data.yend >= display.yend
    ):
        return None
    return (
        f"holds pixels only in x {data.xbegin}..{data.xend - 1}, y {data.ybegin}..{data.yend - 1} "
        f"of its {display.width}x{display.height} frame (a render region, a crop or an "
        "autocropped EXR); save or render the whole frame"
    )


def image_part(path: str | Path) -> tuple[int, object, str | None]:
    """(the part of an image file that holds its colour, that part's ImageSpec, a warning or
    None): the first of a multi-part EXR's parts with R, G and B (`colour_channels`), part 0
    where none has them (one part: part 0). A depth part first was read as a grey image. Raises
    `CaptureError` where OpenImageIO cannot open the file."""
    path = Path(path)
    reader = oiio.ImageInput.open(str(path))
    if reader is None:
        raise CaptureError(
            f"{path}: not an image OpenImageIO can read ({oiio.geterror().strip()}); convert it "
            "to EXR, PNG or TIFF"
        )
    specs = []
    while reader.seek_subimage(len(specs), 0):
        specs.append(reader.spec())
    reader.close()
    oiio.geterror()  # a failed seek past the last part leaves an error pending
    if len(specs) < 2:
        return 0, specs[0], None

    def rgb(spec) -> bool:
        chosen = colour_channels(list(spec.channelnames))
        return not isinstance(chosen, str) and len(chosen[0]) == 3

    coloured = [i for i, spec in enumerate(specs) if rgb(spec)]
    if not coloured or coloured[0] == 0:
        return 0, specs[0], None

    def name(i: int) -> str:
        return specs[i].get_string_attribute("name") or f"part {i}"

    k = coloured[0]
    parts = ", ".join(
        f"'{name(i)}' ({', '.join(spec.channelnames)})" for i, spec in enumerate(specs)
    )
    return (
        k,
        specs[k],
        f"{path}: a multi-part file ({parts}): read '{name(k)}', its first colour part",
    )


def write_image(path: str | Path, linear: np.ndarray) -> Path:
    """Write a linear float image: EXR (float, as is), PNG/TIFF (16-bit sRGB) or JPEG (8-bit sRGB).

    The file appears whole or not at all (written to a temporary file, then renamed).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    data = np.ascontiguousarray(linear, dtype=np.float32)
    if suffix == ".exr":
        fmt = oiio.FLOAT
    elif suffix in (".png", ".tif", ".tiff"):
        fmt, data = oiio.UINT16, srgb_encode(data).astype(np.float32)
    elif suffix in (".jpg", ".jpeg"):
        fmt, data = oiio.UINT8, srgb_encode(data).astype(np.float32)
    else:
        raise CaptureError(
            f"{path}: unsupported image type {suffix!r}; use .exr, .png, .tif or .jpg"
        )
    spec = oiio.ImageSpec(data.shape[1], data.shape[0], data.shape[2], fmt)
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), spec):
            raise CaptureError(f"{path}: cannot write ({oiio.geterror()})")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise CaptureError(f"{path}: cannot write ({out.geterror()})")
    return path


#: The layer a renderer's multi-layer EXR keeps its image in (Blender: `ViewLayer.Combined.R`).
MAIN_LAYERS = ("", "combined", "rgba", "beauty", "image")


def colour_channels(names: list[str]) -> tuple[list[int], int | None] | str:
    """(the colour channels' indices: R, G, B or one grey, the alpha's or None) among an
    image's channel names, or why none can be chosen.

    Channels are read by name, the last part after a dot (`ViewLayer.Combined.R`), upper or lower
    case. One layer holding R, G and B is the image; of several, the one whose name is empty or
    ends in Combined, RGBA, beauty or image (a renderer's main pass; of two, Blender's compositor
    output `Composite.Combined`); depth, normals and other passes beside it are ignored. Without
    RGB, one layer's Y, or a single channel of any name, is grey (with an A beside it, alpha;
    OpenImageIO names two channels not marked alpha R, G: grey and alpha too). Luminance-chroma
    (Y, RY, BY), XYZ and other files are refused: their values are not RGB."""
    layers: dict[str, dict[str, int]] = {}
    for i, name in enumerate(names):
        layer, _, suffix = name.rpartition(".")
        layers.setdefault(layer, {}).setdefault(suffix.upper(), i)
    suffixes = {suffix for layer in layers.values() for suffix in layer}
    if {"RY", "BY"} & suffixes:
        return "a luminance-chroma image (channels Y, RY, BY); save it as RGB"
    rgb = [layer for layer, c in layers.items() if {"R", "G", "B"} <= c.keys()]
    if len(rgb) > 1:
        main = [layer for layer in rgb if layer.rpartition(".")[2].lower() in MAIN_LAYERS]
        if len(main) > 1:  # Blender's compositor output beside the render layer's: the final
            main = [layer for layer in main if layer.lower().startswith("composite")] or main
        if len(main) != 1:
            shown = ", ".join(f"'{layer}'" for layer in rgb)
            which = "several are main ones" if main else "none is the main one (Combined)"
            return f"{len(rgb)} layers hold RGB ({shown}) and {which}; save the image's alone"
        rgb = main
    if rgb:
        c = layers[rgb[0]]
        return [c["R"], c["G"], c["B"]], c.get("A")
    if any({"X", "Y", "Z"} <= c.keys() for c in layers.values()):
        return "channels X, Y, Z (CIE XYZ colour or a vector), not RGB; save it as RGB"
    grey = [layer for layer, c in layers.items() if "Y" in c and "X" not in c]  # not a vector
    if len(grey) == 1:
        c = layers[grey[0]]
        return [c["Y"]], c.get("A")
    if len(names) == 1:  # one channel, whatever its name (R, L, Z...): grey
        return [0], None
    alpha = [i for i, name in enumerate(names) if name.rpartition(".")[2].upper() == "A"]
    if len(names) == 2 and len(alpha) == 1:  # (EXR keeps its channels sorted: A first)
        return [1 - alpha[0]], alpha[0]
    if list(names) == ["R", "G"]:  # OpenImageIO's names for two channels not marked alpha
        return [0], 1
    shown = ", ".join(names[:8]) + (f" and {len(names) - 8} more" if len(names) > 8 else "")
    return f"no RGB or grey (Y) channels among {shown}; save it as RGB"


#: What EXIF's Orientation tag asks a viewer to do with the stored pixels.
ORIENTATIONS = {
    2: "mirrored",
    3: "turned 180 degrees",
    4: "flipped upside down",
    5: "mirrored and turned 90 degrees",
    6: "turned 90 degrees clockwise",
    7: "mirrored and turned 90 degrees",
    8: "turned 90 degrees anticlockwise",
}


def orientation_problem(spec) -> str | None:
    """Why an image whose EXIF Orientation is not 1 is refused (None where it is 1 or absent):
    viewers show it turned, its pixels are read as stored, and which of the two its camera was
    set up on (the size, the up vector) is not known. A phone's upright photo stored sideways
    was read sideways without a word."""
    value = spec.get_int_attribute("Orientation", 1)
    if value not in ORIENTATIONS:
        return None
    return (
        f"its EXIF Orientation is {value}: viewers show it {ORIENTATIONS[value]}, but its pixels "
        f"are read as stored ({spec.width}x{spec.height}); save its pixels upright (exiftran "
        "-ai, or ImageMagick's -auto-orient) if its camera was set up on the image as shown, "
        "or set the tag to 1 (exiftool -n -Orientation=1) if on the pixels as stored"
    )


#: Rec.709's primaries and white (x, y of red, green, blue, white): an image's colours are read
#: as these.
REC709_CHROMATICITIES = (0.64, 0.33, 0.30, 0.60, 0.15, 0.06, 0.3127, 0.3290)


def colour_space_problem(spec) -> str | None:
    """Why an image whose file declares primaries other than Rec.709 is refused (None where it
    declares Rec.709's or none): an EXR's `chromaticities` (ACEScg's AP1) or its
    `colorInteropID` (Blender 5 writes `lin_ap1_scene` from an ACEScg working space) were read
    as Rec.709 without a word, the colours and a peer's base_color truth in other primaries."""
    declared = spec.getattribute("chromaticities")
    if declared is not None and not np.allclose(declared, REC709_CHROMATICITIES, atol=5e-3):
        shown = ", ".join(f"{c:.3f}" for c in declared)
        return (
            f"its chromaticities ({shown}) are not Rec.709's: its colours would be read in "
            "other primaries; convert it to linear Rec.709 (e.g. oiiotool --colorconvert "
            "ACEScg lin_rec709) or render with a Rec.709 working space"
        )
    interop = spec.get_string_attribute("colorInteropID")
    if interop and "rec709" not in interop and interop != "data":
        return (
            f"its colour space is {interop!r}, not Rec.709: its colours would be read in other "
            f"primaries; convert it to linear Rec.709 (e.g. oiiotool --colorconvert {interop} "
            "lin_rec709_scene) or render with a Rec.709 working space"
        )
    return None


def read_linear(path: str | Path, encoding: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(linear RGB float32 (H, W, 3), saturated (H, W) bool, warnings) of an image file.

    `encoding` "linear" keeps values as stored (integers normalised to [0, 1]); "srgb" decodes
    them; "raw" develops camera RAW (see `captures.raw`, as-shot white balance). Integer files
    mark pixels at the top code as saturated; float files those at `HALF_MAX` or above.
    """
    path = Path(path)
    require_utf8(path, CaptureError)
    if encoding not in ENCODINGS:
        raise CaptureError(f"{path}: encoding {encoding!r}; choose one of {', '.join(ENCODINGS)}")
    if encoding == "raw":
        from .raw import develop, read_raw

        raw = read_raw(path)
        return develop(raw), raw.saturated, []
    if path.is_dir():
        raise CaptureError(f"{path}: is a folder, not an image; give an image file")
    if not path.exists():
        raise CaptureError(f"{path}: no such image file; check the path")
    part, spec, note = image_part(path)
    warnings: list[str] = [] if note is None else [note]
    for problem in (orientation_problem(spec), colour_space_problem(spec)):
        if problem is not None:
            raise CaptureError(f"{path}: {problem}")
    chosen = colour_channels(list(spec.channelnames))
    if isinstance(chosen, str):
        raise CaptureError(f"{path}: {chosen}")
    used = [*chosen[0], *([] if chosen[1] is None else [chosen[1]])]
    first = min(used)  # read from the first channel used to the last
    colour, alpha = [i - first for i in chosen[0]], None if chosen[1] is None else chosen[1] - first
    pixels = read_image(path, (first, max(used) + 1), part)
    integer = spec.format.basetype in (oiio.UINT8, oiio.UINT16, oiio.UINT32)
    if alpha is not None:  # an alpha channel: the colours are read as stored, alpha dropped
        seethrough = int(np.count_nonzero(pixels[..., alpha] < 1.0))
        if seethrough:
            warnings.append(
                f"{path}: its alpha channel is ignored ({seethrough} pixels not opaque): the "
                "colour is read as it is stored (a capture.toml takes an object mask as its own "
                "image, views[i].mask; a peer's object is where a view differs from its "
                "environment)"
            )
    pixels = pixels[..., colour]
    if pixels.shape[2] == 1:
        pixels = np.repeat(pixels, 3, axis=2)
    if integer:
        saturated = np.any(pixels >= 1.0, axis=-1)
    else:  # half floats clamp at HALF_MAX: a pixel there is clipped, not measured
        saturated = np.any((pixels >= HALF_MAX) & np.isfinite(pixels), axis=-1)  # inf: NaN/Inf
        if saturated.any():
            warnings.append(
                f"{path}: {int(saturated.sum())} pixels at the half-float maximum {HALF_MAX:g} "
                "are treated as saturated"
            )
    if encoding == "srgb" and not integer:
        raise CaptureError(
            f"{path}: holds floating-point (linear) values but the capture's encoding is "
            '"srgb"; declare encoding = "linear" for float images (EXR, HDR), or give 8/16-bit '
            "sRGB files"
        )
    if encoding == "srgb":
        pixels = srgb_decode(pixels)
    elif spec.format.basetype == oiio.UINT8:
        warnings.append(
            f"{path}: 8-bit data declared linear; 8-bit photos are almost always sRGB-encoded "
            '(declare encoding = "srgb")'
        )
    return pixels.astype(np.float32), saturated, warnings


def read_mask(path: str | Path) -> np.ndarray:
    """A boolean object mask from an image file (any channel > 0.5; a mask whose brightest
    value is below 0.5, e.g. stored as codes 0 and 1, at half its brightest). A cut-out whose
    colour is flat is read from its alpha (it was ignored: the whole frame the object); one
    whose colour and alpha disagree is refused."""
    part, spec, _ = image_part(path) if Path(path).is_file() else (0, None, None)
    pixels = read_image(path, part=part)  # (names the problem of a file that is not there)
    chosen = colour_channels(list(spec.channelnames))
    turned = orientation_problem(spec)
    if turned is not None:
        raise CaptureError(f"{path}: {turned}")
    # its colour channels, alpha left out: a grey-and-alpha PNG's alpha is 1 on every pixel,
    # and read as a channel it made the whole image the object
    colour = pixels[..., chosen[0]] if not isinstance(chosen, str) else pixels[..., :3]
    mask = _threshold(colour)
    alpha = None if isinstance(chosen, str) or chosen[1] is None else pixels[..., chosen[1]]
    if alpha is None or not np.any(alpha < 1.0):
        return mask
    # a cut-out (RGBA, the object in its alpha): its alpha is the mask where its colour is flat
    if float(np.ptp(colour)) == 0.0:
        return _threshold(alpha[..., None])
    if np.count_nonzero(mask != _threshold(alpha[..., None])) > 0.01 * mask.size:
        raise CaptureError(
            f"{path}: its colour and its alpha channel draw different objects; a mask is one: "
            "save the object mask as grey (white on the object) without alpha"
        )
    return mask


def _threshold(pixels: np.ndarray) -> np.ndarray:
    """Any channel above 0.5 (half the brightest value where that is below 0.5: a mask stored as
    codes 0 and 1)."""
    top = float(pixels.max()) if pixels.size else 0.0
    return np.any(pixels > (0.5 if top >= 0.5 or top <= 0 else 0.5 * top), axis=-1)


#: Image types the renderer's bitmap textures and environment maps read.
TEXTURE_SUFFIXES = (
    ".exr",
    ".png",
    ".jpg",
    ".jpeg",
    ".hdr",
    ".rgbe",
    ".pfm",
    ".ppm",
    ".tga",
    ".bmp",
)


def image_problem(path: str | Path) -> str | None:
    """Why `path` is not an image file the renderer can load (None when it is one): missing, a
    folder, an unsupported type, not decodable (truncated, corrupt) or holding values that are
    not finite."""
    path = Path(path)
    shown = not_utf8(path)
    if shown is not None:
        return f"'{shown}' is not a UTF-8 path, which the renderer cannot open; rename it"
    if path.is_dir():
        return f"'{path.name}' is a folder, not an image; give an image file"
    if not path.is_file():
        return f"'{path.name}' does not exist"
    if path.suffix.lower() not in TEXTURE_SUFFIXES:
        return f"'{path.name}' is not a supported image type; use {', '.join(TEXTURE_SUFFIXES)}"
    reader = oiio.ImageInput.open(str(path))
    if reader is None:
        return f"'{path.name}' is not a readable image ({oiio.geterror().strip()}); convert it"
    oiio.geterror()  # nothing pending
    spec = reader.spec()
    reader.close()
    if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
        return f"'{path.name}' has no pixels; give another image"
    grey_alpha = spec.nchannels == 2 and spec.channelnames[1] == "A"
    if spec.nchannels not in (1, 3, 4) and not grey_alpha:  # Mitsuba's bitmap: Y, YA, RGB(A)
        return (
            f"'{path.name}' has {spec.nchannels} channels ({', '.join(spec.channelnames)}); "
            "save it as grey (1 channel), grey and alpha (2: Y, A), RGB (3) or RGBA (4)"
        )
    pixels, problem = _decode(path)
    if problem is not None:
        return f"'{path.name}': {problem}"
    bad = int(np.count_nonzero(~np.isfinite(pixels)))
    if bad:
        return f"'{path.name}' has {bad} values that are not finite (NaN or Inf); fix the image"
    return None
