"""The README's pictures, from actual runs of the add-on (developer tool, not shipped).

For each sample scene: one plain ``uniform`` render and one run of each
``--methods`` entry at ``--spp`` through the API's :func:`api.render` (the job
the CLI and the panel run: :class:`operators.job.RenderJob`), scored against
the bench's converged reference (:func:`bench.references.ensure_reference`).
Writes ``OUT/<scene>.png``, one row per method:

    uniform input at equal spp | result | samples per pixel | relative error vs reference

(the input once, in the first row; the converged reference under it) and
``OUT/index.md`` (scene, method, spp, relMSE, time; the command that made
it).  Samples per pixel: viridis, linear from the map's min to its max (both
printed).  Relative error: per pixel mean over RGB of (x - r)^2 / (r^2 + 0.01)
(the quantity relMSE averages, ``core.metrics``), magma in 16 bands on a log
scale shared by every row of a scene (its 99.5th percentile down 4 decades),
with the run's relMSE printed.  Images go through the scene's view transform as the
add-on's PNG preview does (``--display view``, :func:`api.write_png`) or a
plain sRGB clamp (``--display srgb``, :func:`bench.report.display`).  Labels
are drawn with OpenImageIO's ``render_text`` when it has a font here, else
left to index.md.  From the repository root:

    .venv/bin/python tools/pictures.py --reference-dir /work/refs
    .venv/bin/python tools/pictures.py --scenes cornell --methods auto,lp,rhf --spp 32 --render-references
"""
from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)
from launch import load_package  # noqa: E402

load_package()
from cycles_adaptive.bench import references as refs  # noqa: E402
from cycles_adaptive.bench.cli import DEFAULT_REFERENCE_FLOOR  # noqa: E402
from cycles_adaptive.bench.report import display as srgb_clamp  # noqa: E402
from cycles_adaptive.core import metrics  # noqa: E402

DEFAULT_METHODS = ("auto", "lp")
DEFAULT_OUT = os.path.join(ROOT, "docs", "pictures")
#: decades the shared error colour scale spans below its top (the bench sheet's)
ERROR_DECADES = 4.0
#: percentile of the pooled error maps that is the top of the error scale
ERROR_TOP_PERCENTILE = 99.5
#: bands of the error colour map (ERROR_DECADES / ERROR_LEVELS decades each)
ERROR_LEVELS = 16
BACKGROUND = (30, 30, 30)
TEXT = (235, 235, 235)
FONT_PX = 13
TITLE_H = 20      # rows above each panel for its title
BAR_H = 8         # colour bar under a map panel
FOOT_H = 18       # rows under each panel (bar numbers or a caption)
PAD = 6           # gap between panels and around the sheet
CAPTION_H = 20    # the sheet's bottom line


# ============================================================ pure parts
def colormap(t: np.ndarray, name: str, levels: int | None = None) -> np.ndarray:
    """``t`` in [0, 1] (any shape) -> uint8 RGB of matplotlib's perceptually
    uniform map ``name`` (viridis, magma: lightness rises monotonically with
    ``t``); ``levels``: that many equal bands (each the colour of its centre).
    Non-finite ``t``: NaN and -inf take the low end, +inf the high."""
    from matplotlib import colormaps
    t = np.clip(np.nan_to_num(np.asarray(t, np.float64), nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    if levels:
        n = int(levels)
        t = (np.minimum(np.floor(t * n), n - 1) + 0.5) / n
    rgba = np.asarray(colormaps[name](t), np.float64)
    return np.round(rgba[..., :3] * 255.0).astype(np.uint8)


def linear_unit(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """(v - lo) / (hi - lo) clipped to [0, 1]; a flat range (hi <= lo) maps
    every value to 0.5.  Non-finite values: NaN and -inf -> 0, +inf -> 1."""
    v = np.asarray(values, np.float64)
    span = float(hi) - float(lo)
    if not span > 0 or not np.isfinite(span):
        out = np.full(v.shape, 0.5)
    else:
        out = (np.nan_to_num(v, nan=lo, posinf=hi, neginf=lo) - lo) / span
    return np.clip(out, 0.0, 1.0)


def log_unit(values: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """log10(v) mapped linearly from [log10 lo, log10 hi] to [0, 1], clipped;
    values <= lo (zero included) and NaN -> 0, +inf -> 1.  Needs 0 < lo < hi."""
    if not (0 < lo < hi and np.isfinite(hi)):
        raise ValueError(f"log scale needs 0 < lo < hi, got {lo!r}, {hi!r}")
    v = np.nan_to_num(np.asarray(values, np.float64), nan=lo, posinf=hi, neginf=lo)
    return linear_unit(np.log10(np.maximum(v, lo)), np.log10(lo), np.log10(hi))


def spp_range(samples: np.ndarray) -> tuple:
    """(min, max) of the finite entries of a sample-count map ((0, 0) when none
    is finite): the colour bar's two numbers."""
    s = np.asarray(samples, np.float64)
    s = s[np.isfinite(s)]
    return (float(s.min()), float(s.max())) if s.size else (0.0, 0.0)


def spp_panel(samples: np.ndarray) -> tuple:
    """Sample-count map -> (uint8 RGB viridis image, (min, max)), linear from
    the map's own min to its max (:func:`spp_range`)."""
    lo, hi = spp_range(samples)
    return colormap(linear_unit(samples, lo, hi), "viridis"), (lo, hi)


def error_map(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(H, W) relative squared error of ``image`` against ``reference``,
    mean over RGB of (x - r)^2 / (r^2 + 0.01) (:func:`core.metrics.per_pixel_relmse`:
    a non-finite term counts 1e6), so its mean is the image's relMSE; finite."""
    return metrics.per_pixel_relmse(image, reference)


def error_scale(maps) -> tuple:
    """(lo, hi) of the log colour scale shared by a scene's error maps: hi =
    the ``ERROR_TOP_PERCENTILE`` of their pooled positive finite values, lo =
    hi / 10^``ERROR_DECADES``; (1e-8, 1e-4) when no value is positive."""
    vals = [np.asarray(m, np.float64).ravel() for m in maps]
    pooled = np.concatenate(vals) if vals else np.zeros(0)
    pooled = pooled[np.isfinite(pooled) & (pooled > 0)]
    hi = float(np.percentile(pooled, ERROR_TOP_PERCENTILE)) if pooled.size else 1e-4
    hi = max(hi, 1e-12)
    return hi / 10.0 ** ERROR_DECADES, hi


def error_panel(emap: np.ndarray, scale: tuple) -> np.ndarray:
    """Error map -> uint8 RGB magma image on the shared log ``scale``, in
    ``ERROR_LEVELS`` bands (a quarter decade each: readable, and a noisy map
    then compresses to a PNG the README can carry)."""
    return colormap(log_unit(emap, *scale), "magma", ERROR_LEVELS)


def colour_bar(width: int, height: int, name: str, levels: int | None = None) -> np.ndarray:
    """(height, width, 3) uint8 strip of map ``name`` (in ``levels`` bands),
    low end at the left."""
    t = np.linspace(0.0, 1.0, max(int(width), 1))
    return np.repeat(colormap(t, name, levels)[None], max(int(height), 1), axis=0)


def display_srgb(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> uint8 sRGB (values clipped to [0, 1], non-finite
    as :func:`bench.report.display`: NaN 0, +inf 1)."""
    return np.round(srgb_clamp(rgb) * 255.0).astype(np.uint8)


def upscale(img: np.ndarray, zoom: int) -> np.ndarray:
    """Nearest-neighbour enlargement by a whole ``zoom`` (pixels stay pixels)."""
    z = max(int(zoom), 1)
    return np.repeat(np.repeat(np.asarray(img), z, axis=0), z, axis=1)


class Sheet:
    """A grid of equally sized uint8 RGB panels with a title row above and a
    foot row (colour bar + numbers, or a caption) under each, and a caption
    line at the bottom.  ``boxes[(row, col)]`` = (y, x, h, w) of the panel's
    image on the canvas, ``bars[(row, col)]`` of its colour bar; text only
    ever goes into the title, foot and caption rows."""

    def __init__(self, rows: int, cols: int, height: int, width: int, zoom: int = 2):
        self.rows, self.cols, self.zoom = int(rows), int(cols), max(int(zoom), 1)
        self.ph, self.pw = int(height) * self.zoom, int(width) * self.zoom
        self.cell_h = TITLE_H + self.ph + BAR_H + FOOT_H
        self.cell_w = self.pw
        H = PAD + self.rows * (self.cell_h + PAD) + CAPTION_H
        W = PAD + self.cols * (self.cell_w + PAD)
        self.canvas = np.empty((H, W, 3), np.uint8)
        self.canvas[:] = BACKGROUND
        self.boxes, self.bars, self.texts = {}, {}, []

    def _origin(self, r, c):
        if not (0 <= r < self.rows and 0 <= c < self.cols):
            raise IndexError(f"panel ({r}, {c}) outside a {self.rows}x{self.cols} sheet")
        return PAD + r * (self.cell_h + PAD), PAD + c * (self.cell_w + PAD)

    def put(self, r: int, c: int, img: np.ndarray, title: str = "", foot: str = "",
            bar: str | None = None, bar_numbers: tuple = (), bar_levels: int | None = None) -> tuple:
        """Place ``img`` ((H, W, 3) uint8 at the sheet's panel size before
        zoom) in cell (r, c); ``bar``: a colour map name drawn under it with
        ``bar_numbers`` (left, right) at its ends; ``foot``: text under it
        (centred).  Returns the image's box (y, x, h, w)."""
        img = np.asarray(img)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"panel must be (H, W, 3) uint8, got {img.dtype} {img.shape}")
        big = upscale(img, self.zoom)
        if big.shape[:2] != (self.ph, self.pw):
            raise ValueError(f"panel is {img.shape[1]}x{img.shape[0]}, the sheet's are "
                             f"{self.pw // self.zoom}x{self.ph // self.zoom}")
        y0, x0 = self._origin(r, c)
        y = y0 + TITLE_H
        self.canvas[y:y + self.ph, x0:x0 + self.pw] = big
        self.boxes[(r, c)] = (y, x0, self.ph, self.pw)
        if title:
            self.texts.append((x0 + self.pw // 2, y0 + TITLE_H - 6, title, "center"))
        fy = y + self.ph
        if bar is not None:
            self.canvas[fy + 2:fy + BAR_H, x0:x0 + self.pw] = colour_bar(self.pw, BAR_H - 2, bar, bar_levels)
            self.bars[(r, c)] = (fy + 2, x0, BAR_H - 2, self.pw)
            if len(bar_numbers) == 2:
                self.texts.append((x0, fy + BAR_H + FOOT_H - 5, bar_numbers[0], "left"))
                self.texts.append((x0 + self.pw, fy + BAR_H + FOOT_H - 5, bar_numbers[1], "right"))
            if foot:
                self.texts.append((x0 + self.pw // 2, fy + BAR_H + FOOT_H - 5, foot, "center"))
        elif foot:
            self.texts.append((x0 + self.pw // 2, fy + FOOT_H - 2, foot, "center"))
        return self.boxes[(r, c)]

    def caption(self, text: str) -> None:
        """The sheet's bottom line (left aligned)."""
        self.texts.append((PAD, self.canvas.shape[0] - 6, text, "left"))

    def render(self, labels: bool = True) -> tuple:
        """(canvas with the texts drawn, whether they were drawn).  Text is
        drawn by OpenImageIO's ``render_text`` (its default font); where that
        fails (no font) the canvas is returned without labels."""
        if not labels or not self.texts:
            return self.canvas.copy(), False
        return draw_texts(self.canvas, self.texts)


def draw_texts(canvas: np.ndarray, texts) -> tuple:
    """Draw (x, y_baseline, text, align) entries on a copy of ``canvas`` with
    ``oiio.ImageBufAlgo.render_text``; (image, True), or (the unchanged copy,
    False) when OpenImageIO cannot render text here."""
    out = canvas.copy()
    try:
        import OpenImageIO as oiio
    except ImportError:
        return out, False
    h, w = canvas.shape[:2]
    buf = oiio.ImageBuf(oiio.ImageSpec(w, h, 3, oiio.FLOAT))
    buf.set_pixels(oiio.ROI(0, w, 0, h, 0, 1, 0, 3), canvas.astype(np.float32) / 255.0)
    colour = tuple(v / 255.0 for v in TEXT)
    for x, y, text, align in texts:
        if not oiio.ImageBufAlgo.render_text(buf, int(x), int(y), str(text), FONT_PX, "", colour,
                                             alignx=align, aligny="baseline"):
            return out, False
    px = np.asarray(buf.get_pixels(oiio.FLOAT)).reshape(h, w, 3)
    return np.round(np.clip(px, 0.0, 1.0) * 255.0).astype(np.uint8), True


def write_png(img: np.ndarray, path: str) -> int:
    """uint8 RGB -> PNG at the highest zlib level (OpenImageIO); returns bytes."""
    import OpenImageIO as oiio
    h, w = img.shape[:2]
    spec = oiio.ImageSpec(w, h, 3, oiio.UINT8)
    spec.attribute("png:compressionLevel", 9)
    tmp = path + ".tmp.png"
    out = oiio.ImageOutput.create(tmp)
    if out is None or not out.open(tmp, spec):
        raise OSError(f"{path}: cannot write ({oiio.geterror()})")
    ok = out.write_image(np.ascontiguousarray(img))
    out.close()
    if not ok:
        raise OSError(f"{path}: write failed")
    os.replace(tmp, path)
    return os.path.getsize(path)


def read_png(path: str) -> np.ndarray:
    """An 8-bit image file -> (H, W, 3) uint8 (alpha dropped)."""
    import OpenImageIO as oiio
    src = oiio.ImageInput.open(path)
    if src is None:
        raise OSError(f"{path}: cannot read ({oiio.geterror()})")
    try:
        spec = src.spec()
        px = src.read_image(0, 0, 0, min(spec.nchannels, 3), oiio.UINT8)
    finally:
        src.close()
    return np.asarray(px, np.uint8).reshape(spec.height, spec.width, -1)[..., :3]


def fmt_err(v: float) -> str:
    return f"{v:.2e}" if np.isfinite(v) else "n/a"


def fmt_spp(v: float) -> str:
    return f"{v:.0f}" if abs(v - round(v)) < 0.05 else f"{v:.1f}"


def method_label(rec: dict) -> str:
    """``auto -> lp`` for auto (its choice), else the method's name."""
    ch = rec.get("chosen")
    return f"{rec['method']} -> {ch}" if ch else rec["method"]


def build_sheet(scene: str, uniform: dict, runs: list, reference_spp, spp: float, display_name: str,
                zoom: int = 2, reference: np.ndarray | None = None) -> Sheet:
    """One scene's sheet: a row per run of ``runs`` (dicts with ``image``
    (uint8 display), ``samples``, ``emap``, ``relmse``, ``seconds``, ``method``,
    optional ``chosen``) holding result, samples and error; the first column
    holds the ``uniform`` input (the same keys) once, in the first row (the
    same picture in every row would only repeat it: a noisy panel is a
    third of a sheet's bytes), and ``reference`` (uint8 display) under it;
    further rows leave it empty.  The error panels share one scale
    (:func:`error_scale`)."""
    h, w = uniform["image"].shape[:2]
    sheet = Sheet(len(runs), 4, h, w, zoom)
    scale = error_scale([r["emap"] for r in runs])
    sheet.put(0, 0, uniform["image"], title=f"uniform input, {fmt_spp(uniform['spp_mean'])} spp",
              foot=f"relMSE {fmt_err(uniform['relmse'])}")
    if len(runs) > 1 and reference is not None:
        sheet.put(1, 0, reference, title=f"reference, {reference_spp} spp")
    for i, r in enumerate(runs):
        sheet.put(i, 1, r["image"], title=f"{method_label(r)}, {r['seconds']:.1f} s",
                  foot=f"relMSE {fmt_err(r['relmse'])}")
        img, (lo, hi) = spp_panel(r["samples"])
        sheet.put(i, 2, img, title=f"samples/pixel, mean {fmt_spp(r['spp_mean'])}", bar="viridis",
                  bar_numbers=(fmt_spp(lo), fmt_spp(hi)))
        sheet.put(i, 3, error_panel(r["emap"], scale), title="rel. error vs reference", bar="magma",
                  bar_levels=ERROR_LEVELS,
                  bar_numbers=(f"{scale[0]:.1e}", f"{scale[1]:.1e}"), foot=f"relMSE {fmt_err(r['relmse'])}")
    sheet.caption(f"{scene}, {w}x{h}, {fmt_spp(spp)} spp; {display_name}; "
                  f"reference {reference_spp} spp; error: log scale, same for all rows")
    return sheet


# ========================================================== render parts
def display_view(result, tmpdir: str) -> np.ndarray:
    """A render's result -> uint8 RGB through its scene's view transform, as
    the add-on's PNG preview (:meth:`api.Result.save_preview`), read back."""
    path = os.path.join(tmpdir, "view.png")
    result.save_preview(path, overwrite=True)
    return read_png(path)


def display_view_of(rgb: np.ndarray, scene, tmpdir: str) -> np.ndarray:
    """Any scene-linear RGB through ``scene``'s view transform (:func:`api.write_png`)."""
    from cycles_adaptive import api
    path = os.path.join(tmpdir, "view.png")
    api.write_png(np.asarray(rgb, np.float32), path, scene=scene, overwrite=True)
    return read_png(path)


def run_one(path: str, method: str, args, ref: np.ndarray, tmpdir: str) -> dict:
    """One render through :func:`api.render` (the CLI's job, nothing written)
    and its figures against ``ref``."""
    from cycles_adaptive import api
    res = api.render(path, method=method, spp=float(args.spp), seed=int(args.seed),
                     resolution_percentage=int(args.resolution_percentage))
    s = res.summary
    image = np.asarray(res.image, np.float64)
    disp = display_view(res, tmpdir) if args.display == "view" else display_srgb(image)
    rec = {"method": method, "chosen": s.get("chosen"), "image": disp,
           "samples": np.asarray(res.samples, np.float64), "emap": error_map(image, ref),
           "relmse": metrics.relmse(image, ref), "seconds": float(s["total_seconds"]),
           "render_seconds": float(s["render_seconds"]), "spp_mean": float(s["spp_mean"]),
           "view_transform": res.scene.view_settings.view_transform if res.scene is not None else None}
    print(f"[pictures]   {method_label(rec):>12}: relMSE {rec['relmse']:.3e}, {rec['spp_mean']:.2f} spp, "
          f"{rec['seconds']:.2f} s", flush=True)
    return rec


def reference_of(path: str, args) -> tuple:
    """(reference RGB, sidecar) of the scene at its current frame: a cached
    converged reference in ``--reference-dir`` (the bench's floor), rendered
    there when missing only with ``--render-references``."""
    import bpy
    refs.open_scene(path, force=True)
    frame = bpy.context.scene.frame_current
    ref_path = refs.ensure_reference(path, frame, args.resolution_percentage, args.reference_spp,
                                     directory=args.reference_dir, render_missing=args.render_references,
                                     floor=args.reference_floor, max_spp=args.reference_max_spp,
                                     log=lambda m: print(m, flush=True))
    return refs.load_checked_reference(ref_path)


def run_scene(name: str, args, tmpdir: str) -> dict:
    """Reference, the uniform input and every method's run of one scene; its sheet."""
    path = refs.scene_path(name)
    ref, rec = reference_of(path, args)
    print(f"[pictures] {name}: reference {rec['spp']} spp (halves floor "
          f"{rec.get('noise_relmse_halves') or float('nan'):.1e})", flush=True)
    uniform = run_one(path, "uniform", args, ref, tmpdir)
    runs = [run_one(path, m, args, ref, tmpdir) for m in args.methods]
    vt = uniform["view_transform"]
    disp = (f"display: scene view transform ({vt})" if args.display == "view"
            else "display: plain sRGB clamp")
    if args.display == "view":
        import bpy
        ref_disp = display_view_of(ref, bpy.context.scene, tmpdir)
    else:
        ref_disp = display_srgb(ref)
    sheet = build_sheet(name, uniform, runs, rec["spp"], args.spp, disp, args.zoom, ref_disp)
    img, labelled = sheet.render(labels=not args.no_labels)
    out = os.path.join(args.out, f"{name}.png")
    size = write_png(img, out)
    print(f"[pictures] {name}: {out} ({size / 1024:.0f} KB{'' if labelled else ', no labels'})", flush=True)
    return {"scene": name, "png": out, "bytes": size, "labelled": labelled, "display": disp,
            "reference_spp": rec["spp"], "reference_floor": rec.get("noise_relmse_halves"),
            "rows": [uniform] + runs}


def index_markdown(results: list, command: str, args) -> str:
    """docs/pictures/index.md: what each picture shows, the table and the command."""
    import bpy
    lines = [
        "# Pictures from actual runs",
        "",
        "Made by `tools/pictures.py` (regenerate with the command below when results change; nothing here is "
        "edited by hand). Each `<scene>.png` has one row per method: the plain `uniform` render at the same "
        "spp (the noisy input; first row only, the converged reference under it), the method's result, "
        "its samples per pixel (viridis, linear from the map's "
        "minimum to its maximum, both printed under the colour bar) and its relative error against the "
        "converged reference (per pixel, mean over RGB of (x - r)^2 / (r^2 + 0.01), the term relMSE averages; "
        f"magma in {ERROR_LEVELS} bands on a log scale over {ERROR_DECADES:g} decades below the "
        f"{ERROR_TOP_PERCENTILE:g}th percentile of the scene's maps, the same scale in every row; the "
        "printed bounds are the scale's ends, values beyond them are clamped). "
        + ("Images: the scene's view transform, as the add-on's PNG preview (`api.write_png`). "
           if args.display == "view" else "Images: a plain sRGB clamp of the linear values. ")
        + f"Panels are the {args.resolution_percentage} % render enlarged {args.zoom}x (nearest).",
        "",
        f"Command: `{command}`",
        "",
        "The references are the benchmark's converged ones (`bench/references.py`: two independent halves, "
        f"doubled until their noise floor is below {args.reference_floor:g} relMSE or {args.reference_max_spp} "
        "spp); a fresh clone without them adds `--render-references` (they are then rendered into "
        "`--reference-dir`, default `references/`: 22 s to 20 min a scene on 2 cores, about 40 min for the six). "
        "`auto -> X` names the candidate auto chose from the first pass.",
        "",
        f"Machine: {os.cpu_count()} CPU threads visible ({platform.processor() or platform.machine()}), "
        f"Blender {bpy.app.version_string} (bpy module), seed {args.seed}, made "
        f"{time.strftime('%Y-%m-%d %H:%M')}. Times are wall seconds of the whole job (`total_seconds` of the "
        "API's summary: set-up, renders, adaptation, reconstruction) on a shared machine, so they vary "
        "between runs. The renders are deterministic (fixed seed): `uniform` and a fixed method give the same "
        "relMSE every run, but `auto` weighs its candidates' predicted error against their seconds measured on "
        "this machine, so under another load it may choose another candidate (and show another relMSE).",
        "",
        "| scene | picture | method | spp (mean) | relMSE | time (s) | reference |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in results:
        pic = f"[{os.path.basename(r['png'])}]({os.path.basename(r['png'])})"
        for i, row in enumerate(r["rows"]):
            label = "uniform (input)" if i == 0 else method_label(row)
            lines.append(f"| {r['scene'] if i == 0 else ''} | {pic if i == 0 else ''} | {label} | "
                         f"{row['spp_mean']:.2f} | {row['relmse']:.3e} | {row['seconds']:.2f} | "
                         + (f"{r['reference_spp']} spp" if i == 0 else "") + " |")
    if not all(r["labelled"] for r in results):
        lines += ["", "Labels could not be drawn here (OpenImageIO found no font): columns left to right are "
                  "uniform input, result, samples per pixel, relative error."]
    lines += ["", "Total size of the pictures: "
              f"{sum(r['bytes'] for r in results) / 1024:.0f} KB.", ""]
    return "\n".join(lines)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", help="comma-separated sample scenes (default: the bench's six)")
    p.add_argument("--methods", default=",".join(DEFAULT_METHODS),
                   help=f"comma-separated methods, one row each (default {','.join(DEFAULT_METHODS)})")
    p.add_argument("--spp", type=float, default=16.0, help="mean samples per pixel of every run (default 16)")
    p.add_argument("--resolution-percentage", type=int, default=100,
                   help="render size, %% of the scene's (default 100: 128x128; the references' size)")
    p.add_argument("--seed", type=int, default=0, help="Cycles seed of the runs (default 0)")
    p.add_argument("--zoom", type=int, default=2, help="whole-number enlargement of each panel (default 2)")
    p.add_argument("--display", choices=("view", "srgb"), default="view",
                   help="view: the scene's view transform (the PNG preview's); srgb: plain sRGB clamp")
    p.add_argument("--reference-dir", default=None, help="reference cache (default references/)")
    p.add_argument("--render-references", action="store_true",
                   help="render a missing reference (minutes a scene) instead of failing")
    p.add_argument("--reference-spp", type=int, default=refs.DEFAULT_SPP,
                   help=f"spp a reference starts from (default {refs.DEFAULT_SPP})")
    p.add_argument("--reference-floor", type=float, default=DEFAULT_REFERENCE_FLOOR,
                   help=f"noise floor a reference must reach (default {DEFAULT_REFERENCE_FLOOR:g}, the bench's)")
    p.add_argument("--reference-max-spp", type=int, default=refs.DEFAULT_MAX_SPP,
                   help=f"cap of the floor loop (default {refs.DEFAULT_MAX_SPP})")
    p.add_argument("--out", default=DEFAULT_OUT, help="output folder (default docs/pictures/)")
    p.add_argument("--no-labels", action="store_true", help="no text on the pictures")
    args = p.parse_args(argv)
    args.methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    if not args.methods:
        p.error("--methods: give at least one method")
    if not args.spp > 0:
        p.error("--spp must be > 0")
    if args.zoom < 1:
        p.error("--zoom must be >= 1")
    if args.seed in refs.half_seeds(refs.REFERENCE_SEED):
        p.error(f"--seed {args.seed} is a seed of the references' halves; the runs need another")
    try:
        args.scenes = refs.scene_names(args.scenes)
    except ValueError as exc:
        p.error(str(exc))
    return args


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    args = parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    command = " ".join([".venv/bin/python", "tools/pictures.py"] + argv)
    results = []
    with tempfile.TemporaryDirectory(prefix="pictures-") as tmpdir:
        for name in args.scenes:
            results.append(run_scene(name, args, tmpdir))
    with open(os.path.join(args.out, "index.md"), "w") as f:
        f.write(index_markdown(results, command, args))
    total = sum(r["bytes"] for r in results)
    print(f"[pictures] {len(results)} pictures, {total / 1024:.0f} KB in all; {args.out}/index.md", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
