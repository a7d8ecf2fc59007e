"""The report of a fit: one self-contained HTML page (inline CSS, no scripts, nothing fetched)
with its PNGs beside it in `report/`; every file written whole or not at all."""

from __future__ import annotations

import html
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from captures.files import atomic_path, write_text
from captures.images import srgb_encode

from ..material.free import bound_note
from .figures import SOFTWARE, pyplot, save_figure

DIFF_RANGE = 0.2  # the difference map's colour range, in units of the view's exposure
DIFF_CMAP = "coolwarm"  # the difference map's colours: blue darker than the photo, red brighter
INVALID_GREY = 0.6  # pixels the fit does not use (weight 0)
PAGE_WIDTH = 1000  # px: the page's content; narrower views are scaled up with sharp pixels
CORR_CMAP = "RdBu_r"  # the correlation table's colours: blue negative, red positive
CORR_WRITTEN = 20  # the most rows whose correlations are written in their cells
UNDETERMINED_GREY = 0.75  # an undetermined parameter's correlations (unknown, not 0)
MASK_WIDTH, MASK_HEIGHT = 200, 300  # px: the most a fitted mask or texture is shown
DASH, PLUS_MINUS = "\u2014", "\u00b1 "


@dataclass
class ViewPanel:
    """One view of the fit: the photo, the fitted render (gains applied), the validity weight."""

    name: str
    photo: np.ndarray  # (H, W, 3) linear float32
    render: np.ndarray  # (H, W, 3) linear float32, the fitted render (gains applied)
    weight: np.ndarray  # (H, W) validity weight in [0, 1]
    held_out: bool  # not used by the fit (scored only)
    rmse: float  # relative RMSE of render vs photo over valid pixels


CSS = """body { font: 14px/1.4 sans-serif; margin: 0 auto; padding: 1em 2em; max-width: 1100px; }
h1 { margin-bottom: .2em; } h2 { margin-top: 1.6em; border-bottom: 1px solid #ccc; }
.meta { color: #555; } .meta span { margin-right: 1.5em; }
img { max-width: 100%; height: auto; display: block; }
figure { margin: 1em 0; padding: .5em; border: 2px solid #8ab; border-radius: 6px; }
figure.held { border: 2px dashed #d80; background: #fff8ee; }
figcaption { font-weight: 600; margin-bottom: .3em; }
.badge { background: #d80; color: #fff; border-radius: 4px; padding: 0 .5em; margin-left: .6em; }
.scroll { overflow-x: auto; } table { border-collapse: collapse; font-size: 13px; }
th, td { border: 1px solid #ddd; padding: 2px 8px; text-align: right; vertical-align: top; }
th { background: #f2f2f2; text-align: center; }
td.key, td.text { text-align: left; font-family: monospace; }
td.text { font-family: inherit; max-width: 28em; overflow-wrap: anywhere; }
tr.poor td, span.poor { background: #fff3c4; } tr.off td, span.off { background: #ffd9d9; }
td.bad { color: #b00; font-weight: 600; }
.masks { display: flex; flex-wrap: wrap; gap: 1em; } .masks figure { border-color: #ccc; }
.masks img { image-rendering: pixelated; border: 1px solid #999; }
.titles { display: grid; font-size: 12px; text-align: center; color: #333; }
img.view { width: 100%; } img.pixelated { image-rendering: pixelated; }
.legend .bar { display: inline-block; width: 160px; height: .8em; margin: 0 .4em;
  vertical-align: middle; border: 1px solid #999; } .legend .bar.invalid { width: 1.2em; }
table.corr td { min-width: 2.4em; padding: 2px 3px; text-align: center; font-size: 11px; }
table.corr th { background: none; font: 12px monospace; }
table.corr th.key { text-align: left; } table.corr th.up { vertical-align: bottom; }
table.corr th.up span { writing-mode: vertical-rl; transform: rotate(180deg);
  white-space: nowrap; }"""


def _e(value) -> str:
    return html.escape(str(value))


def _slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_.") or "x"


def _array(value) -> np.ndarray | None:
    try:
        return None if value is None else np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        return None


def _fmt(value, signed: bool = False) -> str:
    """A number as text; RGB as 3 numbers; textures as "N texels, mean m"; unknown as a dash."""
    arr = _array(value)
    if arr is None:
        return DASH if value is None else _e(value)
    form = "{:+.3g}" if signed else "{:.4g}"
    if arr.size <= 3:
        return ", ".join(form.format(v) for v in arr.ravel())
    texels = arr.size if arr.ndim <= 1 else arr.size // arr.shape[-1]
    return f"{texels} texels, mean {form.format(float(np.nanmean(arr)))}"


def _view_columns(width: int) -> tuple[int, int]:
    """A view's panel width and the gap between its panels, in the image's own pixels."""
    return width, max(2, round(width / 40))


def _diff_colours(diff: np.ndarray) -> np.ndarray:
    """(render - photo) / exposure as RGB in [0, 1]: `DIFF_CMAP` over +-`DIFF_RANGE`, NaN grey."""
    import matplotlib

    scaled = np.clip((diff / DIFF_RANGE + 1) / 2, 0, 1)
    rgb = matplotlib.colormaps[DIFF_CMAP](np.nan_to_num(scaled, nan=0.5))[..., :3]
    return np.where(np.isnan(diff)[..., None], INVALID_GREY, rgb)


def _view_png(view: ViewPanel, path: Path) -> Path:
    """Photo | fitted render | (render - photo) / exposure side by side, each at the view's own
    pixels (the page scales them and draws their titles and colour bar: drawn by matplotlib, a
    view took 0.16 s), invalid pixels grey; tagged `Software = layerfit` like every figure."""
    from matplotlib.image import imsave

    valid = np.asarray(view.weight) > 0
    photo, render = np.asarray(view.photo, np.float32), np.asarray(view.render, np.float32)
    exposure = max(float(np.percentile(photo[valid], 99)) if valid.any() else 1.0, 1e-12)
    diff = np.where(valid, (render - photo).mean(axis=-1) / exposure, np.nan)
    h, w = valid.shape
    panel, gap = _view_columns(w)
    sheet = np.ones((h, 3 * panel + 2 * gap, 3), np.float32)
    shown = (srgb_encode(photo / exposure), srgb_encode(render / exposure), _diff_colours(diff))
    for k, image in enumerate(shown):
        x = k * (panel + gap)
        sheet[:, x : x + panel] = np.clip(np.nan_to_num(image), 0, 1)
    with atomic_path(path) as partial:
        imsave(partial, sheet, format="png", metadata={"Software": SOFTWARE})
    return path


def _view_html(view: ViewPanel, png: Path) -> str:
    """A view's figure: its caption, the panels' titles over their columns, the panels."""
    badge = "<span class='badge'>held out</span>" if view.held_out else ""
    w = np.shape(view.weight)[1]
    panel, gap = _view_columns(w)
    columns = f"{panel}fr {gap}fr {panel}fr {gap}fr {panel}fr"
    titles = ("photo", "", "fitted render", "", "(render \u2212 photo) / exposure")
    heads = "".join(f"<span>{t}</span>" for t in titles)
    small = " pixelated" if 3 * panel + 2 * gap < PAGE_WIDTH else ""
    return (
        f"<figure class='{'held' if view.held_out else 'fit'}'><figcaption>{_e(view.name)}"
        f" \u2014 relative RMSE {_fmt(view.rmse)}{badge}</figcaption>"
        f"<div class='titles' style='grid-template-columns: {columns}'>{heads}</div>"
        f"<img class='view{small}' src='report/{_e(png.name)}' "
        f"alt='{_e(view.name)}: photo, render, difference'></figure>"
    )


def _diff_legend() -> str:
    """The difference panels' colour bar: a CSS gradient of `DIFF_CMAP` with its range."""
    import matplotlib

    cmap = matplotlib.colormaps[DIFF_CMAP]
    stops = ", ".join(_hex(cmap(t)) for t in np.linspace(0, 1, 9))
    grey = _hex((INVALID_GREY,) * 3)
    return (
        "<p class='legend'>(render \u2212 photo) / exposure: "
        f"<span>\u2212{DIFF_RANGE:g}</span><span class='bar' "
        f"style='background: linear-gradient(to right, {stops})'></span>"
        f"<span>+{DIFF_RANGE:g}</span> (exposure: the photo's 99th percentile); "
        f"<span class='bar invalid' style='background: {grey}'></span> pixels not fitted</p>"
    )


def _loss_png(summary: dict, path: Path) -> Path | None:
    """Semilog loss per step, one colour per phase; a phase of one point as a marker."""
    history = _array(summary.get("history"))
    if history is None or history.ndim != 1 or not np.any(np.isfinite(history) & (history > 0)):
        return None
    history = np.where(np.isfinite(history) & (history > 0), history, np.nan)
    ends = [int(e) for e in summary.get("phase_ends") or []] or [history.size]
    phases = summary.get("phases") or []
    plt = pyplot()
    # fixed margins (with a constrained layout the plot took 0.31 s, without 0.20 s)
    fig, ax = plt.subplots(figsize=(7, 3.4))
    fig.subplots_adjust(left=0.11, right=0.98, bottom=0.14, top=0.91)
    begin = 0
    for k, stop in enumerate(ends):
        end = min(stop, history.size)
        p = phases[k] if k < len(phases) and isinstance(phases[k], dict) else {}
        label = f"{k + 1}: {p.get('solver', '?')}, {p.get('spp', '?')} spp, "
        factor = p.get("downscale")  # times the fit's own (fit.downscale)
        if isinstance(factor, int) and isinstance(summary.get("downscale"), int):
            factor *= summary["downscale"]
        label += f"1/{factor if factor is not None else '?'} res"
        ax.semilogy(
            np.arange(begin, end), history[begin:end], "o" if end - begin == 1 else "-", label=label
        )
        begin = end
    ax.set_xlabel("step")
    ax.set_ylabel("loss (weighted)")
    ax.set_title("per phase, at its own resolution and spp", fontsize=9)
    ax.legend(fontsize=8)
    return save_figure(fig, path, dpi=100)


def _correlation_table(corr: np.ndarray, labels: list[str]) -> str:
    """The correlation matrix as a table: each cell coloured by `CORR_CMAP` over -1..1 (blue
    negative, red positive), its value written where the matrix has at most `CORR_WRITTEN` rows
    (always in its title, shown on hover), an undetermined parameter's row and column (NaN, null
    in the summary) grey; the columns' labels upwards, and a colour bar. Drawn by matplotlib it
    took 0.2 s of a fit's report."""
    import matplotlib

    cmap = matplotlib.colormaps[CORR_CMAP]
    n = corr.shape[0]
    written = n <= CORR_WRITTEN
    grey = _hex((UNDETERMINED_GREY,) * 3)
    head = "".join(f"<th class='up'><span>{_e(label)}</span></th>" for label in labels)
    rows = []
    for i in range(n):
        cells = []
        for j in range(n):
            v = float(corr[i, j])
            pair = f"{_e(labels[i])} / {_e(labels[j])}"
            if not np.isfinite(v):
                cells.append(
                    f"<td class='undetermined' style='background: {grey}' "
                    f"title='{pair}: undetermined'></td>"
                )
                continue
            ink = "#fff" if abs(v) > 0.6 else "#000"
            text = f"{v:.2f}" if written else ""
            cells.append(
                f"<td style='background: {_hex(cmap((v + 1) / 2))}; color: {ink}' "
                f"title='{pair}: {v:.3f}'>{text}</td>"
            )
        rows.append(f"<tr><th class='key'>{_e(labels[i])}</th>{''.join(cells)}</tr>")
    stops = ", ".join(_hex(cmap(t)) for t in np.linspace(0, 1, 9))
    legend = (
        "<p class='legend'>correlation: <span>\u22121</span><span class='bar' "
        f"style='background: linear-gradient(to right, {stops})'></span><span>+1</span>"
    )
    if not np.all(np.isfinite(corr)):
        legend += (
            f"; <span class='bar invalid' style='background: {grey}'></span> undetermined "
            "(no correlation known)"
        )
    return (
        f"{legend}</p><div class='scroll'><table class='corr'><tr><th></th>{head}</tr>"
        f"{''.join(rows)}</table></div>"
    )


def _hex(rgb) -> str:
    """An RGB (or RGBA) colour in [0, 1] as `#rrggbb`."""
    return "#{:02x}{:02x}{:02x}".format(*(round(255 * float(c)) for c in tuple(rgb)[:3]))


def _mask_png(mask: np.ndarray, path: Path) -> Path:
    """A mask in [0, 1] as a grey image, or a colour texture (linear RGB) in sRGB, one pixel per
    texel."""
    mask = np.asarray(mask, dtype=np.float32)
    if mask.ndim == 3 and mask.shape[-1] == 3:
        from captures.images import srgb_encode

        with atomic_path(path) as partial:
            pyplot().imsave(partial, np.clip(srgb_encode(mask), 0, 1), format="png")
        return path
    mask = mask.mean(axis=-1) if mask.ndim == 3 else mask
    with atomic_path(path) as partial:
        pyplot().imsave(partial, np.clip(mask, 0, 1), cmap="gray", vmin=0, vmax=1, format="png")
    return path


def _table(head: list[str], rows: list[tuple[str, list[str]]]) -> str:
    """An HTML table; `rows` are (row class, cells as HTML)."""
    out = ["<div class='scroll'><table><tr>", *(f"<th>{_e(h)}</th>" for h in head), "</tr>"]
    out += [f"<tr class='{cls}'>{''.join(cells)}</tr>" for cls, cells in rows]
    return "".join(out) + "</table></div>"


def _td(text: str, cls: str = "") -> str:
    return f"<td class='{cls}'>{text}</td>"


def _parameter_rows(summary: dict) -> list[tuple[str, list[str]]]:
    """key, start, fitted, std, truth, error, error/std; poorly determined and > 3 std marked."""
    values, start = summary.get("values") or {}, summary.get("start") or {}
    std, truth, error = (summary.get(k) or {} for k in ("std", "truth", "error"))
    poor = set(summary.get("poorly_determined") or [])
    rows = []
    for key in dict.fromkeys([*values, *start]):
        err, sd, ratio = _array(error.get(key)), _array(std.get(key)), None
        if err is not None and sd is not None and err.shape == sd.shape:
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = np.where(np.isfinite(sd) & (sd > 0), err / sd, np.nan)  # as summary's
        off = ratio is not None and bool(np.any(np.abs(ratio) > 3))
        if ratio is not None and np.all(np.isnan(ratio)):
            ratio = None
        cls = " ".join(c for c, on in (("poor", key in poor), ("off", off)) if on)
        cells = [_td(_e(key), "key"), _td(_fmt(start.get(key))), _td(_fmt(values.get(key)))]
        cells += [_td(DASH if sd is None else PLUS_MINUS + _fmt(sd)), _td(_fmt(truth.get(key)))]
        cells += [_td(_fmt(err, signed=True)), _td(_fmt(ratio, signed=True), "bad" if off else "")]
        rows.append((cls, cells))
    return rows


def _outcome_rows(summary: dict) -> list[tuple[str, list[str]]]:
    rows = []
    for o in summary.get("outcomes") or []:
        bad = "bad" if o.get("outcome") in ("diverged", "failed") else ""
        cells = [
            _td(_e(o.get("solver", DASH)), "key"),
            _td(_e(o.get("outcome", DASH)), f"key {bad}"),
        ]
        cells += [_td(_fmt(o.get(k))) for k in ("steps", "rejected", "seconds")]
        rows.append(("", [*cells, _td(_e(o.get("message") or ""), "text")]))
    return rows


def _header(summary: dict, title: str) -> str:
    wall = summary.get("wall_time_s")
    wall = f"{wall:.1f} s" if isinstance(wall, int | float) else DASH
    soft = ", ".join(f"{_e(k)} {_e(v)}" for k, v in (summary.get("software") or {}).items())
    return (
        f"<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'><title>{_e(title)}</title>"
        f"<style>{CSS}</style></head><body><h1>{_e(title)}</h1><p class='meta'>"
        f"<span>capture: <b>{_e(summary.get('capture') or DASH)}</b></span>"
        f"<span>wall time: <b>{wall}</b></span><span>final loss: <b>{_fmt(summary.get('loss'))}"
        f"</b></span><br><span>software: {soft or DASH}</span></p>"
    )


def _img(png: Path | None, alt: str, missing: str, width: int | None = None) -> str:
    style = f" style='width: {width}px'" if width else ""
    return (
        f"<img src='report/{_e(png.name)}' alt='{_e(alt)}'{style}>" if png else f"<p>{missing}</p>"
    )


def write_report(
    out: Path,
    summary: dict,
    views: list[ViewPanel],
    masks: dict[str, np.ndarray] | None = None,
    title: str | None = None,
) -> Path:
    """Write out/report.html and its PNGs beside it (out/report/...) ; returns the html path."""
    out, summary = Path(out), summary or {}
    assets = out / "report"
    title = title or Path(str(summary.get("config") or "fit")).name
    page = [_header(summary, title)]
    notes = summary.get("capture_warnings") or []
    if notes:
        items = "".join(f"<li>{_e(n)}</li>" for n in notes)
        page.append(f"<h2>About the capture</h2><ul class='notes'>{items}</ul>")
    page.append("<h2>Views</h2>")
    page.append(_diff_legend() if views else "")
    for i, view in enumerate(views):
        png = _view_png(view, assets / f"view-{i:02d}-{_slug(view.name)}.png")
        page.append(_view_html(view, png))
    page.append("" if views else "<p>No views.</p>")

    page.append("<h2>Loss per phase</h2>")
    page.append(_img(_loss_png(summary, assets / "loss.png"), "loss", "No loss history."))

    page.append(
        "<h2>Parameters</h2><p class='meta'><span class='poor'>poorly determined</span>"
        "<span class='off'>|error| &gt; 3 std</span></p>"
    )
    choices = {k: v for k, v in (summary.get("options") or {}).items() if isinstance(v, str)}
    if choices:
        model = ", ".join(f"{k} = {v}" for k, v in choices.items())
        page.append(f"<p class='meta'>model: {_e(model)}</p>")
    head = ["key", "start", "fitted", "\u00b1 std", "truth", "error", "error / std"]
    page.append(_table(head, _parameter_rows(summary)))
    bounds = summary.get("at_bounds") or []
    if bounds:
        starts = len(summary.get("starts") or ()) or 1
        items = "".join(f"<li>{_e(bound_note(b, starts))}</li>" for b in bounds)
        page.append(f"<ul class='notes'>{items}</ul>")

    page.append("<h2>Phase outcomes</h2>")
    head = ["solver", "outcome", "steps", "rejected", "seconds", "message"]
    page.append(_table(head, _outcome_rows(summary)))

    page.append("<h2>Correlation</h2>")
    corr = _array(summary.get("correlation"))
    if corr is not None and corr.ndim == 2 and corr.shape[0] == corr.shape[1] and corr.size:
        labels = [str(x) for x in summary.get("correlation_labels") or []]
        labels = labels if len(labels) == len(corr) else [str(i) for i in range(len(corr))]
        page.append(_correlation_table(corr, labels))
    else:
        page.append("<p>No correlation matrix (no uncertainty estimate).</p>")

    if masks:
        page.append("<h2>Fitted masks and textures</h2><div class='masks'>")
        for i, (key, texels) in enumerate(masks.items()):
            caption, shown = key, np.asarray(texels, np.float32)
            if key.endswith(" sd") or (shown.ndim == 3 and shown.shape[-1] == 3):
                # a colour or an sd: its brightest texels white
                scale = 1.0 / max(float(np.percentile(shown, 99.5)), 1e-6)
                shown, caption = shown * scale, f"{key} (x {scale:.3g})"
            # named by its key, not its caption (`stain.mask: truth (IoU ...)`: stain.mask_truth)
            name = _slug(re.sub(r"\s*\(.*\)", "", key))
            png = _mask_png(shown, assets / f"mask-{i:02d}-{name}.png")
            height, width = shown.shape[:2]  # a tall texture (the cup's 32x128) at most as tall:
            shown_width = min(MASK_WIDTH, round(MASK_HEIGHT * width / height))
            page.append(
                f"<figure>{_img(png, key, '', shown_width)}"
                f"<figcaption>{_e(caption)}</figcaption></figure>"
            )
        page.append("</div>")
    page.append("</body></html>\n")
    return write_text(out / "report.html", "\n".join(page))
