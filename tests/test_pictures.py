"""tools/pictures.py: the README's pictures.  The pure parts (panel assembly,
colour maps and their legends, error maps, non-finite input) against
independent computations, and one tiny end-to-end run (32x32, 2 spp)."""
import importlib.util
import os

import numpy as np
import pytest

from cycles_adaptive.core import metrics

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _load():
    spec = importlib.util.spec_from_file_location("pictures_tool", os.path.join(ROOT, "tools", "pictures.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


P = _load()


def luminance(rgb):
    """Rec. 709 relative luminance of sRGB-encoded uint8 colours (linearised)."""
    c = np.asarray(rgb, np.float64) / 255.0
    lin = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)
    return lin @ np.array([0.2126, 0.7152, 0.0722])


def test_each_panel_lands_exactly_at_its_box():
    rng = np.random.default_rng(1)
    h, w, zoom = 12, 10, 3
    sheet = P.Sheet(2, 4, h, w, zoom)
    panels = {(r, c): rng.integers(0, 256, (h, w, 3), dtype=np.uint8) for r in range(2) for c in range(4)}
    for (r, c), img in panels.items():
        sheet.put(r, c, img, title=f"panel {r} {c}", foot="foot", bar="viridis" if c == 2 else None,
                  bar_numbers=("1", "9") if c == 2 else ())
    canvas, _ = sheet.render(labels=True)
    for (r, c), img in panels.items():
        y, x, bh, bw = sheet.boxes[(r, c)]
        assert (bh, bw) == (h * zoom, w * zoom)
        # independent of upscale(): canvas pixel (y + zoom i + a, x + zoom j + b) is panel pixel (i, j)
        for a in range(zoom):
            for b in range(zoom):
                np.testing.assert_array_equal(canvas[y + a:y + bh:zoom, x + b:x + bw:zoom], img)
    # boxes do not overlap, and the text (drawn or not) never touched an image box
    keys = list(sheet.boxes)
    for i, k in enumerate(keys):
        for k2 in keys[i + 1:]:
            y, x, bh, bw = sheet.boxes[k]
            y2, x2, bh2, bw2 = sheet.boxes[k2]
            assert y + bh <= y2 or y2 + bh2 <= y or x + bw <= x2 or x2 + bw2 <= x
    assert set(sheet.bars) == {(0, 2), (1, 2)}
    for by, bx, _, bw in sheet.bars.values():  # the colour bar under the map panels, low end left
        np.testing.assert_array_equal(canvas[by, bx:bx + bw], P.colour_bar(bw, 1, "viridis")[0])


def test_panel_of_wrong_size_or_type_is_refused():
    sheet = P.Sheet(1, 2, 8, 8, 2)
    with pytest.raises(ValueError):
        sheet.put(0, 0, np.zeros((8, 9, 3), np.uint8))
    with pytest.raises(ValueError):
        sheet.put(0, 0, np.zeros((8, 8, 3), np.float32))
    with pytest.raises(IndexError):
        sheet.put(1, 0, np.zeros((8, 8, 3), np.uint8))


@pytest.mark.parametrize("name", ["viridis", "magma"])
@pytest.mark.parametrize("levels", [None, 16])
def test_colour_maps_are_monotone_in_luminance(name, levels):
    t = np.linspace(0.0, 1.0, 1001)
    y = luminance(P.colormap(t, name, levels))
    # rounding to 8 bits may swap neighbours by one code value (< 1e-3 in luminance) ...
    assert np.all(np.diff(y) >= -1e-3)
    # ... never more: every step of 1/50 brightens
    assert np.all(np.diff(luminance(P.colormap(np.linspace(0.0, 1.0, 51), name))) > 0)
    assert y[-1] > y[0] + 0.5  # dark to bright, not flat
    if levels:  # exactly `levels` bands
        assert len(np.unique(P.colormap(t, name, levels), axis=0)) == levels


def test_spp_legend_numbers_are_the_maps_min_and_max():
    rng = np.random.default_rng(2)
    s = rng.integers(3, 61, (16, 20)).astype(np.float64)
    s[4, 5], s[9, 9] = 3.0, 61.0
    img, (lo, hi) = P.spp_panel(s)
    assert (lo, hi) == (s.min(), s.max())
    np.testing.assert_array_equal(img[4, 5], P.colormap(0.0, "viridis"))
    np.testing.assert_array_equal(img[9, 9], P.colormap(1.0, "viridis"))
    # the sheet prints exactly those numbers at the ends of the spp colour bar
    rgb = rng.integers(0, 256, (16, 20, 3), dtype=np.uint8)
    run = {"image": rgb, "samples": s, "emap": rng.random((16, 20)), "relmse": 0.01, "seconds": 1.0,
           "method": "lp", "spp_mean": float(s.mean())}
    uni = dict(run, method="uniform", samples=np.full((16, 20), 16.0))
    sheet = P.build_sheet("x", uni, [run], 1024, 16, "display: test", zoom=1)
    y, x, _, bw = sheet.bars[(0, 2)]
    ends = {align: text for tx, _, text, align in sheet.texts if align != "center" and x <= tx <= x + bw}
    assert ends == {"left": "3", "right": "61"}


def test_flat_spp_map_takes_the_middle_colour_and_prints_its_value():
    img, (lo, hi) = P.spp_panel(np.full((4, 4), 16.0))
    assert lo == hi == 16.0
    assert np.all(img == P.colormap(0.5, "viridis"))


def test_error_map_of_an_image_against_itself_is_zero():
    x = np.random.default_rng(3).random((9, 7, 3)) * 4
    e = P.error_map(x, x)
    assert e.shape == (9, 7) and np.all(e == 0.0)
    lo, hi = P.error_scale([e])  # no positive value: still a valid log scale
    assert 0 < lo < hi and np.isfinite(hi)
    assert np.all(P.error_panel(e, (lo, hi)) == P.colormap(0.0, "magma", P.ERROR_LEVELS))


def test_error_map_is_the_relmse_term_and_averages_to_relmse():
    rng = np.random.default_rng(4)
    r = rng.random((6, 5, 3))
    x = r + rng.normal(0, 0.1, r.shape)
    manual = ((x - r) ** 2 / (r ** 2 + 0.01)).mean(axis=-1)
    np.testing.assert_allclose(P.error_map(x, r), manual, rtol=1e-12)
    assert P.error_map(x, r).mean() == pytest.approx(metrics.relmse(x, r), rel=1e-12)


def test_log_scale_ends_and_midpoint_and_shared_scale():
    lo, hi = 1e-5, 1e-1
    u = P.log_unit(np.array([0.0, lo, np.sqrt(lo * hi), hi, 10.0]), lo, hi)
    np.testing.assert_allclose(u, [0, 0, 0.5, 1, 1], atol=1e-12)
    a, b = np.full((4, 4), 1e-3), np.full((4, 4), 1e-2)
    s_lo, s_hi = P.error_scale([a, b])
    assert s_hi == pytest.approx(np.percentile(np.r_[a.ravel(), b.ravel()], P.ERROR_TOP_PERCENTILE))
    assert s_lo == pytest.approx(s_hi / 10 ** P.ERROR_DECADES)
    with pytest.raises(ValueError):
        P.log_unit(a, 0.0, 1.0)


def test_non_finite_input_gives_finite_output():
    bad = np.array([[np.nan, np.inf], [-np.inf, 0.5]])
    rgb = np.stack([bad, bad, bad], axis=-1)
    ref = np.full_like(rgb, 0.5)
    for out in (P.linear_unit(bad, 0, 1), P.log_unit(bad, 1e-3, 1.0)):
        assert np.all(np.isfinite(out)) and out.min() >= 0 and out.max() <= 1
    e = P.error_map(rgb, ref)
    assert np.all(np.isfinite(e))
    assert P.error_map(rgb, ref)[1, 1] == 0.0
    scale = P.error_scale([e, bad])
    assert np.all(np.isfinite(scale)) and 0 < scale[0] < scale[1]
    for img in (P.colormap(bad, "viridis"), P.spp_panel(bad)[0], P.error_panel(e, scale), P.display_srgb(rgb)):
        assert img.dtype == np.uint8 and img.shape[:2] == (2, 2)
    lo, hi = P.spp_range(bad)
    assert (lo, hi) == (0.5, 0.5)
    d = P.display_srgb(rgb)
    assert d[0, 0, 0] == 0 and d[0, 1, 0] == 255 and d[1, 0, 0] == 0


def test_png_round_trip_is_exact(tmp_path):
    img = np.random.default_rng(5).integers(0, 256, (7, 11, 3), dtype=np.uint8)
    path = str(tmp_path / "a.png")
    assert P.write_png(img, path) == os.path.getsize(path)
    np.testing.assert_array_equal(P.read_png(path), img)


def test_end_to_end_tiny(tmp_path):
    """cornell at 25 % (32x32), uniform and lp at 2 spp, a 4-spp reference
    rendered into a temporary cache: one PNG of the sheet's size and an index
    whose relMSE rows match the arrays' own figures."""
    out, refdir = tmp_path / "pics", tmp_path / "refs"
    argv = ["--scenes", "cornell", "--methods", "uniform,lp", "--spp", "2", "--resolution-percentage", "25",
            "--reference-dir", str(refdir), "--render-references", "--reference-spp", "4",
            "--reference-floor", "10", "--out", str(out), "--display", "srgb"]
    assert P.main(argv) == 0
    img = P.read_png(str(out / "cornell.png"))
    assert img.shape == P.Sheet(2, 4, 32, 32, 2).canvas.shape
    text = (out / "index.md").read_text()
    assert "| cornell |" in text and "tools/pictures.py --scenes cornell" in text
    rows = [line.split("|") for line in text.splitlines() if line.startswith("|") and "relMSE" not in line
            and "---" not in line]
    assert [c[3].strip() for c in rows] == ["uniform (input)", "uniform", "lp"]
    e = [float(c[5]) for c in rows]
    assert all(np.isfinite(e)) and e[0] == e[1] > 0  # the same seed: uniform twice, identical
    # the input panel is the uniform run's image in plain sRGB: equal to its first row's result panel
    sheet, blank = P.Sheet(2, 4, 32, 32, 2), np.zeros((32, 32, 3), np.uint8)
    y0, x0, h, w = sheet.put(0, 0, blank)
    y1, x1, _, _ = sheet.put(0, 1, blank)
    np.testing.assert_array_equal(img[y0:y0 + h, x0:x0 + w], img[y1:y1 + h, x1:x1 + w])
