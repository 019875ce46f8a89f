"""The benchmark's outputs: progress lines, ``results.json``, ``results.md``,
``plot_<scene>.png`` (relMSE against seconds, log-log) and ``sheet_<scene>.png``
(images, sample maps, true and estimated error of one budget).
"""
from __future__ import annotations

import json
import os

import numpy as np

from ..core import io as imageio
from ..core import metrics


def log(msg: str) -> None:
    """One progress line of the benchmark (flushed: runs take minutes)."""
    print(f"[bench] {msg}", flush=True)


def err_text(exc: BaseException) -> str:
    """An exception as one short line for results.json and the tables."""
    msg = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {msg[0] if msg else ''}"[:400]


def finite(x):
    """A JSON-safe figure: float(x), or None for None / NaN / inf."""
    return float(x) if x is not None and np.isfinite(x) else None


def display(rgb: np.ndarray) -> np.ndarray:
    """Scene-linear RGB -> display (the scenes' 'Standard' view transform: sRGB
    OETF on values clipped to [0, 1])."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, np.float64)[..., :3]), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def write_outputs(res: dict, out: str) -> dict:
    """Plots and sheets (when matplotlib is there), results.json (every figure,
    no pixel arrays) and results.md in ``out``; returns their paths."""
    paths = {"plots": [], "sheets": []}
    try:
        import matplotlib
        matplotlib.use("Agg")
        for s, d in res["scenes"].items():
            if d.get("status") != "ok":
                continue
            p = os.path.join(out, f"plot_{s}.png")
            plot_scene(s, d, p)
            paths["plots"].append(p)
            p = os.path.join(out, f"sheet_{s}.png")
            sheet_scene(s, d, p)
            paths["sheets"].append(p)
    except ImportError as exc:
        res["errors"].append({"error": f"no pictures: {err_text(exc)}"})
    for d in res["scenes"].values():
        if isinstance(d, dict) and d.get("status") == "ok":
            d["reference_check"] = reference_check(d)
    # the JSON keeps every figure, not the pixel arrays
    clean = json.loads(json.dumps(res, default=_json_default))
    for s, d in clean["scenes"].items():
        if isinstance(d, dict) and "sheet" in d:
            d["sheet"] = {"budget": d["sheet"]["budget"], "file": f"sheet_{s}.png"}
    clean["pictures"] = {"plots": [os.path.basename(p) for p in paths["plots"]],
                         "sheets": [os.path.basename(p) for p in paths["sheets"]]}
    jp = os.path.join(out, "results.json")
    imageio.write_text(jp, json.dumps(clean, indent=1))
    mp = os.path.join(out, "results.md")
    imageio.write_text(mp, markdown(clean))
    paths.update(results_json=jp, results_md=mp)
    return paths


def _json_default(o):
    if isinstance(o, np.ndarray):
        return None
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    return str(o)


STYLE = {"uniform": "C0", "var": "C1", "awr": "C2", "lp": "C3", "rhf": "C4",
         "cycles_oidn": "C5", "oidn": "C9", "auto": "C7", "cycles_adaptive": "C6", "cycles_adaptive+oidn": "C8"}


def plot_scene(name, d, path):
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=(7, 5), dpi=110)
    cu = sorted(d["uniform_curve"], key=lambda p: p["spp"])
    ax.plot([p["seconds"]["total"] for p in cu], [p["relmse"] for p in cu], "k-o", lw=2,
            label="plain Cycles uniform")
    for p in cu:
        ax.annotate(f"{p['spp']}", (p["seconds"]["total"], p["relmse"]), fontsize=7,
                    textcoords="offset points", xytext=(3, 3))
    names = list(dict.fromkeys(r["name"] for r in d["runs"]))
    for n in names:
        pts = sorted(((r["seconds"]["total"], r["relmse"], r["budget"]) for r in d["runs"]
                      if r["name"] == n and r.get("status") == "ok"), key=lambda p: p[2])
        if not pts:
            continue
        base = n.replace("oracle-", "").replace("uniform-", "")
        style = "--" if n.startswith("oracle-") else ":" if n.startswith("uniform-") else "-"
        marker = "s" if n in ("cycles_oidn", "cycles_adaptive", "cycles_adaptive+oidn") else "o"
        ax.plot([p[0] for p in pts], [p[1] for p in pts], style, marker=marker, ms=4,
                color=STYLE.get(base, None), alpha=0.6 if n.startswith("oracle-") else 1.0, label=n)
    rf = reference_record(d)
    floor = rf.get("noise_relmse_halves") or rf.get("noise_relmse")
    if floor:
        ax.axhline(floor, color="grey", ls=":", lw=1, label="reference noise floor" + (
            "" if rf.get("noise_relmse_halves") else " (variance of the mean, old reference)"))
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("seconds (wall, whole run)")
    ax.set_ylabel("relMSE")
    ax.set_title(f"{name} ({d['width']}x{d['height']}): relMSE vs time, budgets "
                 f"{', '.join(str(b) for b in sorted({r['budget'] for r in d['runs']}))} spp", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def sheet_scene(name, d, path):
    """Reference / noisy / each result (row 1), sample maps (row 2), true error
    (row 3) and estimated error (row 4, relative, same colour scale)."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import LogNorm
    sh = d["sheet"]
    ref = sh["reference"]
    imgs = sh["images"]
    order = [n for n in ["noisy"] + list(dict.fromkeys(r["name"] for r in d["runs"])) if n in imgs]
    cols = 1 + len(order)
    fig, axes = plt.subplots(4, cols, figsize=(1.9 * cols, 8.2), dpi=100, squeeze=False)
    for a in axes.ravel():
        a.set_xticks([])
        a.set_yticks([])
        a.axis("off")
    axes[0, 0].imshow(display(ref), interpolation="nearest")
    axes[0, 0].set_title(f"reference {d['reference'].get('spp')} spp", fontsize=7)
    axes[0, 0].axis("on")
    axes[1, 0].text(0.5, 0.5, f"sample maps\n(spp, budget {sh['budget']})", ha="center", va="center",
                    fontsize=8, transform=axes[1, 0].transAxes)
    axes[2, 0].text(0.5, 0.5, "true error\n(x-r)^2/(r^2+.01)", ha="center", va="center", fontsize=8,
                    transform=axes[2, 0].transAxes)
    axes[3, 0].text(0.5, 0.5, "estimated error\n(relative)", ha="center", va="center", fontsize=8,
                    transform=axes[3, 0].transAxes)
    true_maps = {n: metrics.per_pixel_relmse(np.asarray(imgs[n]["image"]), ref) for n in order}
    allv = np.concatenate([v[v > 0].ravel() for v in true_maps.values()] or [np.array([1e-4])])
    vmax = float(np.percentile(allv, 99.5)) if allv.size else 1.0
    vmin = max(vmax * 1e-4, 1e-8)
    norm = LogNorm(vmin=vmin, vmax=vmax)
    for j, n in enumerate(order, start=1):
        pic = imgs[n]
        if n == "noisy":  # plain uniform Cycles at the sheet's budget
            r = next((p for p in d["uniform_curve"] if p["spp"] == sh["budget"]), {})
        else:
            r = next((r for r in d["runs"] if r["name"] == n and r["budget"] == sh["budget"]), {})
        a = axes[0, j]
        a.imshow(display(pic["image"]), interpolation="nearest")
        a.set_title(f"{n}\nrelMSE {r.get('relmse', float('nan')):.2e}, {r.get('seconds', {}).get('total', float('nan')):.1f} s",
                    fontsize=6)
        a.axis("on")
        if "samples" in pic:  # each map on its own scale, printed under it
            smax = max(float(np.max(pic["samples"])), 1.0)
            axes[1, j].imshow(pic["samples"], cmap="viridis", vmin=0, vmax=smax, interpolation="nearest")
            axes[1, j].axis("on")
            axes[1, j].set_xlabel("relative (Cycles' sample-count pass)" if pic.get("samples_relative")
                                  else f"0..{smax:.0f} spp (mean {np.mean(pic['samples']):.1f})", fontsize=6)
        axes[2, j].imshow(np.maximum(true_maps[n], vmin), cmap="magma", norm=norm, interpolation="nearest")
        axes[2, j].axis("on")
        if "estimated" in pic:
            axes[3, j].imshow(np.maximum(pic["estimated"], vmin), cmap="magma", norm=norm,
                              interpolation="nearest")
            axes[3, j].axis("on")
    fig.suptitle(f"{name}: budget {sh['budget']} spp (rows 3-4: log colour scale "
                 f"{vmin:.1e}..{vmax:.1e})", fontsize=9)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def _fmt(v, spec=".3g"):
    if v is None:
        return "-"
    if isinstance(v, float) and not np.isfinite(v):
        return "-"
    return format(v, spec)


def markdown(res: dict) -> str:
    m = res["machine"]
    cfg = res["config"]
    L = ["# Benchmark results", "",
         f"Command: `{res['command'].strip()}`  ",
         f"Started {res['started']}, session {res['session_seconds']:.0f} s; Blender {m['blender']}, "
         f"numpy {m['numpy']}, Python {m['python']}; {m['cpu_count']} CPUs ({m.get('cpu_model', m['processor'])}), "
         f"{m['platform']}; load average at start {res.get('loadavg_start')}, at end "
         f"{res.get('loadavg_end')}; peak RSS {res['peak_rss_mb']:.0f} MB.", "",
         "## How it was measured", ""]
    for k, v in res["protocol"].items():
        L.append(f"- **{k}**: {v}")
    L += ["- Timings are single measurements on a shared machine (see the load averages); ratios "
          "within one session are what to compare.", ""]

    budgets = cfg["budgets"]
    L += ["## Summary: equal-error speed-up vs plain uniform Cycles (relMSE in brackets)", "",
          "| scene | method | " + " | ".join(f"{b} spp" for b in budgets) + " |",
          "|---|---|" + "---|" * len(budgets)]
    for row in res["summary"]:
        if "speedup" not in row:
            L.append(f"| {row['scene']} | scene failed: {row.get('error')} |" + " |" * len(budgets))
            continue
        cells = []
        for b in budgets:
            k = str(b)
            if k in row["speedup"]:
                cells.append(f"{_fmt(row['speedup'][k], '.2f')}x ({_fmt(row['relmse'][k], '.2e')})")
            elif k in row["errors"]:
                cells.append("error")
            else:
                cells.append("")
        L.append(f"| {row['scene']} | {row['name']} | " + " | ".join(cells) + " |")
    L.append("")

    L += ["## Targets (goals, not test asserts)", ""]
    for t in res["targets"]:
        met = {True: "**met**", False: "**not met**", None: "not measured"}[t["met"]]
        L.append(f"- {t['target']}: {met}")
        for dline in t["detail"]:
            L.append(f"  - {dline}")
    L.append("")
    L += _why_section(res)
    L += references_section(res)

    for s, d in res["scenes"].items():
        L += [f"## {s}", ""]
        if d.get("status") != "ok":
            L += [f"Failed: {d.get('error')}", ""]
            continue
        rf = reference_record(d)
        chk = d.get("reference_check") or reference_check(d)
        if chk["below"] is not True:
            L += [f"**Warning: {chk['verdict']}**", ""]
        L += [f"{d['width']}x{d['height']}, frame {d['frame']}; reference {rf.get('spp')} spp seed "
              f"{rf.get('seed')} (noise floor relMSE {_fmt(rf.get('noise_relmse_halves'), '.2e')} from two "
              f"independent halves, {_fmt(rf.get('noise_relmse'), '.2e')} from the variance of the mean); warm-up "
              f"render {d['warmup_seconds']:.2f} s (not counted); scene measured in "
              f"{d.get('scene_seconds', 0):.0f} s (+ {d.get('reference_seconds_this_session', 0):.0f} s "
              f"for the reference); plain renders use the "
              f"'{d['sampling_pattern_plain']}' pattern.", "",
              "Plain uniform Cycles (the t_uniform curve):", "",
              "| spp | relMSE | SMAPE | seconds | efficiency |", "|---|---|---|---|---|"]
        for p in d["uniform_curve"]:
            L.append(f"| {p['spp']} | {p['relmse']:.3e} | {p['smape']:.4f} | {p['seconds']['total']:.2f} | "
                     f"{_fmt(p['efficiency'], '.1f')} |")
        L += ["", "| run | budget | spp | relMSE | SMAPE | seconds (render / adapt / recon / overhead) "
                  "| efficiency | speed-up | error corr. | LP centres | regions | recon. memory B/px | notes |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in d["runs"]:
            if r.get("status") != "ok":
                L.append(f"| {r['name']} | {r['budget']} | | | | | | | | | | | ERROR: {r.get('error')} |")
                continue
            sec = r["seconds"]
            split = " / ".join(_fmt(sec.get(k), ".2f") for k in ("render", "adapt", "reconstruct", "overhead"))
            notes = []
            if r.get("partial"):
                notes.append(f"PARTIAL: stopped at {r['spp_mean']:.1f} of {r['budget']} spp by the run time cap")
            if "threshold" in r:
                notes.append(f"threshold {r['threshold']:.3g}, max {r.get('max_samples')} spp")
            if "relmse_without_denoiser" in r:
                notes.append(f"plain render without OIDN: relMSE {r['relmse_without_denoiser']:.2e}")
            if "time_ratio" in r:
                notes.append(f"time {r['time_ratio']:.2f}x target" + ("" if r.get("time_matched") else
                                                                      " (not matched)"))
            mem = r.get("memory", {})
            L.append(f"| {r['name']} | {r['budget']} | {_fmt(r['spp_mean'], '.2f')} | {r['relmse']:.3e} | "
                     f"{r['smape']:.4f} | {sec['total']:.2f} ({split}) | {_fmt(r.get('efficiency'), '.1f')} | "
                     f"{_fmt(r.get('speedup'), '.2f')} | {_fmt(r.get('error_correlation'), '.2f')} | "
                     f"{_fmt(r.get('center_fraction'), '.3f')} | {r.get('regions', '-')} | "
                     f"{_fmt(mem.get('bytes_per_pixel'), '.0f')} | {'; '.join(notes)} |")
        L += estimates_section(d) + gains_section(d) + cost_section(d)
        L += ["", f"![relMSE vs seconds](plot_{s}.png)", "", f"![sheet](sheet_{s}.png)", ""]

    sc = res.get("scaling")
    if sc:
        L += ["## Scaling: reconstruction time and memory by image size", "", sc["how"] + ".", ""]
        meths = list(dict.fromkeys(m for r in sc["rows"] for m in r.get("methods", {})))
        L += ["| size | MP | OIDN s (s/MP) | " + " | ".join(f"{m} s (s/MP, B/px)" for m in meths) + " |",
              "|---|---|---|" + "---|" * len(meths)]
        for r in sc["rows"]:
            if "methods" not in r:
                L.append(f"| {r['percentage']}% | | error: {r.get('error')} |" + " |" * len(meths))
                continue
            o = r["oidn"]
            oc = f"{o['seconds']:.2f} ({o['seconds_per_mp']:.2f})" if "seconds" in o else f"error: {o.get('error')}"
            cells = []
            for m in meths:
                v = r["methods"].get(m, {})
                if "seconds" in v:
                    cells.append(f"{v['seconds']:.2f} ({v['seconds_per_mp']:.2f}, "
                                 f"{_fmt(v.get('bytes_per_pixel'), '.0f')})")
                else:
                    cells.append(f"skipped: {v['skipped']}" if "skipped" in v else f"error: {v.get('error')}")
            L.append(f"| {r['width']}x{r['height']} | {r['megapixels']:.3f} | {oc} | " + " | ".join(cells) + " |")
        L.append("")
    if res.get("errors"):
        L += ["## Errors", ""] + [f"- {e}" for e in res["errors"]] + [""]
    return "\n".join(L) + "\n"


#: a reference judges an error when its noise floor is below this fraction of it
FLOOR_FRACTION = 0.1


def reference_record(d) -> dict:
    """A scene's reference figures (``d["reference"]``), completed from its
    sidecar (``path``) with the keys the session did not copy (the halves floor)."""
    rf = dict(d.get("reference") or {})
    if rf.get("noise_relmse_halves") is None and rf.get("path"):
        from . import references as refs
        side = refs.read_sidecar(rf["path"]) or {}
        for k in ("noise_relmse_halves", "floor_target", "half_spp", "spp", "noise_relmse", "render_seconds"):
            if rf.get(k) is None and side.get(k) is not None:
                rf[k] = side[k]
    return rf


def reference_check(d) -> dict:
    """Is the scene's reference converged below what it judges?  Its halves
    floor against ``FLOOR_FRACTION`` x the smallest relMSE scored on the scene
    (every run that finished and the plain uniform curve).  ``below``: True /
    False, None when not judged (no halves floor: a reference from before the
    two-halves sidecar; or no error scored); ``verdict``: one line."""
    rf = reference_record(d)
    errs = [r.get("relmse") for r in d.get("runs", []) if r.get("status") == "ok"]
    errs += [p.get("relmse") for p in d.get("uniform_curve", [])]
    errs = [float(e) for e in errs if isinstance(e, (int, float)) and np.isfinite(e) and e > 0]
    smallest = min(errs) if errs else None
    bound = None if smallest is None else FLOOR_FRACTION * smallest
    floor = rf.get("noise_relmse_halves")
    floor = float(floor) if isinstance(floor, (int, float)) and np.isfinite(floor) else None
    spp = rf.get("spp")
    if floor is None:
        below = None
        verdict = (f"reference at {spp} spp has no two-halves noise floor (an older reference; "
                   f"variance-of-the-mean figure {_fmt(rf.get('noise_relmse'), '.2e')}, which "
                   "under-states QMC noise): not judged, re-render it with ./cycles-adaptive "
                   "references --floor")
    elif bound is None:
        below = None
        verdict = f"reference at {spp} spp, floor {floor:.2e}: no error scored to judge it against"
    else:
        below = floor < bound
        verdict = (f"reference at {spp} spp, noise floor {floor:.2e} "
                   + ("is below" if below else "is NOT below")
                   + f" 1/{1 / FLOOR_FRACTION:.0f} of the smallest relMSE scored ({smallest:.2e} -> "
                   f"{bound:.2e})" + ("" if below else f"; a relMSE below {floor / FLOOR_FRACTION:.1e} "
                                      f"is more than {FLOOR_FRACTION:.0%} the reference's own noise "
                                      "(re-render it with a lower --reference-floor)"))
    return {"spp": spp, "floor": floor, "floor_target": rf.get("floor_target"),
            "noise_relmse": rf.get("noise_relmse"), "smallest_relmse": smallest, "bound": bound,
            "below": below, "verdict": verdict}


def references_section(res) -> list:
    """"References": each scene's reference spp and noise floor, and whether
    the floor is below 1/10 of the smallest error scored there (a warning line
    per scene where it is not)."""
    rows, warn = [], []
    for s, d in res.get("scenes", {}).items():
        if not isinstance(d, dict) or d.get("status") != "ok":
            continue
        c = d.get("reference_check") or reference_check(d)
        mark = {True: "yes", False: "**NO**", None: "not judged"}[c["below"]]
        rows.append(f"| {s} | {c['spp']} | {_fmt(c['floor'], '.2e')} | {_fmt(c['noise_relmse'], '.2e')} | "
                    f"{_fmt(c['floor_target'], '.2e')} | {_fmt(c['smallest_relmse'], '.2e')} | "
                    f"{_fmt(c['bound'], '.2e')} | {mark} |")
        if c["below"] is not True:
            warn.append(f"- **Warning ({s})**: {c['verdict']}.")
    if not rows:
        return []
    return (["## References", "",
             "Noise floor = expected relMSE of a perfect image against the reference, from two "
             "independently seeded halves: relMSE(half A, half B) / 4. A reference judges a scene "
             f"when its floor is below {FLOOR_FRACTION:g} x the smallest relMSE scored there.", "",
             "| scene | spp | floor (two halves) | floor (variance of the mean) | floor target "
             "| smallest relMSE scored | 1/10 of it | floor below? |",
             "|---|---|---|---|---|---|---|---|"] + rows + [""] + warn + ([""] if warn else []))


def goal_cell(g, spec=".3g", scale=1.0) -> str:
    """A goal's figure and verdict for a table: ``0.31 missed``; ``-`` when
    not measured; ``(not judged)`` after a figure without a verdict."""
    if not g or g.get("value") is None:
        return "-"
    v = _fmt(g["value"] * scale, spec)
    return v + {True: " met", False: " **missed**", None: " (not judged)"}[g.get("met")]


def _loop_runs(d):
    return [r for r in d.get("runs", []) if r.get("status") == "ok" and "goals" in r]


#: the per-run goals the estimates table has its own columns for
ESTIMATE_COLUMNS = ("error_correlation_block", "guard_fraction", "negative_share", "brightness_percent",
                    "beyond_map_percent")


def estimates_section(d) -> list:
    """"Estimates and artefacts": the per-run goals of every run of our loop."""
    from .targets import GOALS, RUN_GOALS
    rows = _loop_runs(d)
    if not rows:
        return []
    more = [k for k in RUN_GOALS if k not in ESTIMATE_COLUMNS]  # goals added later: one column each
    L = ["", "Estimates and artefacts (each goal: the figure and met / missed; see the protocol):", "",
         "| run | budget | error corr. per pixel | error corr. 8x8 (>= 0.8) | estimated / true relMSE "
         "| guard % (< 5) | negative % (= 0) "
         "| most negative | brightness % (within 0.5) | beyond map % (< 10) | map CV | uniform share % |"
         + "".join(f" {k} ({GOALS[k][0]} {GOALS[k][1]}) |" for k in more),
         "|---|---|---|---|---|---|---|---|---|---|---|---|" + "---|" * len(more)]
    for r in rows:
        g = r["goals"]
        tail = "".join(f" {goal_cell(g.get(k))} |" for k in more)
        L.append(f"| {r['name']} | {r['budget']} | {_fmt(r.get('error_correlation'), '.3f')} | "
                 f"{goal_cell(g.get('error_correlation_block'), '.3f')} | "
                 f"{_fmt(r.get('error_calibration'), '.2f')} | "
                 f"{goal_cell(g.get('guard_fraction'), '.2f', 100.0)} | "
                 f"{goal_cell(g.get('negative_share'), '.2f', 100.0)} | {_fmt(r.get('negative_min'), '.3g')} | "
                 f"{goal_cell(g.get('brightness_percent'), '+.2f')} | "
                 f"{goal_cell(g.get('beyond_map_percent'), '.1f')} | {_fmt(r.get('map_cv'), '.3f')} | "
                 f"{_fmt(None if r.get('map_uniform_share') is None else 100 * r['map_uniform_share'], '.0f')} |"
                 + tail)
    return L


def gains_section(d) -> list:
    """The relMSE ratios of estimated, oracle and uniform-sampling runs."""
    comp = d.get("comparisons") or []
    if not comp:
        return []
    L = ["", "Where the samples go (same reconstruction, equal budget; relMSE ratios):", "",
         "| method | budget | relMSE | oracle | uniform sampling | estimated / oracle (<= 1.15) "
         "| uniform / oracle (>= 1.3) | uniform / estimated |", "|---|---|---|---|---|---|---|---|"]
    for c in comp:
        g = c["goals"]
        L.append(f"| {c['method']} | {c['budget']} | {_fmt(c['relmse'], '.3e')} | "
                 f"{_fmt(c['relmse_oracle'], '.3e')} | {_fmt(c['relmse_uniform'], '.3e')} | "
                 f"{goal_cell(g.get('estimated_over_oracle'), '.2f')} | "
                 f"{goal_cell(g.get('uniform_over_oracle'), '.2f')} | {_fmt(c['uniform_over_method'], '.2f')} |")
    return L


def cost_section(d) -> list:
    """Time split (% of the run) and adaptation + reconstruction per
    megapixel against OIDN's denoise per megapixel of the same budget."""
    rows = _loop_runs(d)
    if not rows:
        return []
    L = ["", "Time split and cost vs OIDN (same session, same budget):", "",
         "| run | budget | seconds | render % | adapt % | reconstruct % | overhead % "
         "| adapt+recon s/MP | OIDN denoise s/MP | ratio (<= 1) | speed-up (>= 1) |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        sec = r["seconds"]
        tot = sec["total"] if sec.get("total") else None
        pct = [_fmt(100 * sec.get(k, 0.0) / tot if tot else None, ".0f")
               for k in ("render", "adapt", "reconstruct", "overhead")]
        L.append(f"| {r['name']} | {r['budget']} | {_fmt(tot, '.2f')} | " + " | ".join(pct)
                 + f" | {_fmt(r.get('adapt_reconstruct_s_per_mp'), '.2f')} | "
                   f"{_fmt(r.get('oidn_denoise_s_per_mp'), '.2f')} | "
                   f"{goal_cell(r['goals'].get('oidn_cost_ratio'), '.2f')} | "
                   f"{goal_cell(r['goals'].get('speedup'), '.2f')} |")
    return L


def _why_section(res) -> list:
    """Measured reasons next to the targets: where the time goes, how good the
    estimated maps are."""
    L = ["### Where the time goes (our loop's runs, all scenes and budgets)", "",
         "| method | runs | render | adapt | reconstruct | overhead | adapt+recon / OIDN per MP "
         "(worst) | mean error corr. (8x8) |",
         "|---|---|---|---|---|---|---|---|"]
    acc = {}
    for d in res["scenes"].values():
        for r in d.get("runs", []):
            if r.get("status") == "ok" and r["kind"] in ("method", "oracle", "uniform_sampling"):
                a = acc.setdefault(r["name"], {"n": 0, "render": 0.0, "adapt": 0.0, "reconstruct": 0.0,
                                               "overhead": 0.0, "total": 0.0, "corr": [], "block": [],
                                               "cost": []})
                a["n"] += 1
                for k in ("render", "adapt", "reconstruct", "overhead", "total"):
                    a[k] += r["seconds"].get(k, 0.0)
                a["corr"].append(r.get("error_correlation"))
                a["block"].append(r.get("error_correlation_block"))
                a["cost"].append(r.get("oidn_cost_ratio"))
    for n, a in acc.items():
        tot = a["total"] or 1.0
        corr = [c for c in a["corr"] if c is not None]
        block = [c for c in a["block"] if c is not None]
        cost = [c for c in a["cost"] if c is not None]
        L.append(f"| {n} | {a['n']} | " + " | ".join(f"{100 * a[k] / tot:.0f}%" for k in
                                                     ("render", "adapt", "reconstruct", "overhead"))
                 + f" | {_fmt(max(cost) if cost else None, '.2f')}"
                 + f" | {_fmt(float(np.mean(corr)) if corr else None, '.2f')}"
                 + f" ({_fmt(float(np.mean(block)) if block else None, '.2f')}) |")
    L.append("")
    return L
