"""Figures computed from the measured runs: the equal-error speed-up curve
``t_uniform(e)``, geometric means, the targets and the summary rows.

Equal-error speed-up = t_uniform(e) / t, with t_uniform interpolated log-log
between the plain uniform renders of the same session and extrapolated with
slope -1 (time inversely proportional to error, as for Monte Carlo).
"""
from __future__ import annotations

import math

import numpy as np


def speedup_curve(points):
    """``t_uniform(e)`` from plain uniform renders ``[(relmse, seconds), ...]``.

    Log-log linear interpolation between the renders sorted by error; outside
    their range, slope -1 (time inversely proportional to error, as for Monte
    Carlo) from the nearest end.  Returns a function e -> seconds (NaN for a
    non-finite or non-positive e).
    """
    pts = sorted((float(e), float(t)) for e, t in points
                 if np.isfinite(e) and np.isfinite(t) and e > 0 and t > 0)
    if not pts:
        return lambda e: float("nan")
    le = np.log([p[0] for p in pts])
    lt = np.log([p[1] for p in pts])
    # errors must fall as time grows; enforce it (noisy timings) with a running max
    # of time from the large-error end, so the curve is a function
    lt = np.maximum.accumulate(lt[::-1])[::-1]

    def t_uniform(e):
        if not (np.isfinite(e) and e > 0):
            return float("nan")
        x = math.log(e)
        if x <= le[0]:
            return float(math.exp(lt[0] + (le[0] - x)))
        if x >= le[-1]:
            return float(math.exp(lt[-1] - (x - le[-1])))
        return float(math.exp(np.interp(x, le, lt)))

    return t_uniform


ADAPTIVE_METHODS = ("var", "awr", "lp", "rhf")


def _gmean(v):
    """Geometric mean of the finite positive values of ``v``; None without any."""
    v = [x for x in v if x is not None and np.isfinite(x) and x > 0]
    return float(np.exp(np.mean(np.log(v)))) if v else None


def evaluate_targets(res: dict) -> list:
    """The benchmark's targets (goals, not test asserts), each with met
    (True/False/None = not measured) and why."""
    scenes = {k: v for k, v in res["scenes"].items() if v.get("status") == "ok"}
    out = []

    def runs(kind=None, name=None):
        for s, d in scenes.items():
            for r in d["runs"]:
                if r.get("status") == "ok" and (kind is None or r["kind"] == kind) and \
                        (name is None or r["name"] == name):
                    yield s, r

    # 1. every method >= 5x on every scene
    per = {}
    for s, r in runs("method"):
        if r["method"] in ADAPTIVE_METHODS:
            per.setdefault(r["method"], {}).setdefault(s, []).append(r.get("speedup"))
    failed_methods = set()
    for s, d in scenes.items():
        for r in d["runs"]:
            if r["kind"] == "method" and r.get("status") != "ok" and r["method"] in ADAPTIVE_METHODS:
                failed_methods.add(r["method"])
    detail, ok_all = [], True
    for m in ADAPTIVE_METHODS:
        if m not in per:
            if m in failed_methods:
                ok_all = False
                detail.append(f"{m}: no successful run")
            continue
        g = {s: _gmean(v) for s, v in per[m].items()}
        low = [s for s, v in g.items() if v is None or v < 5]
        ok_all &= not low
        detail.append(f"{m}: " + ", ".join(f"{s} {v:.2f}x" if v else f"{s} n/a" for s, v in g.items()))
    out.append({"target": "every adaptive method >= 5x equal-error speed-up vs uniform on every scene "
                          "(geometric mean over budgets)",
                "met": bool(per) and ok_all if per else None, "detail": detail})

    # 2. best method >= OIDN on at least half of the scenes
    wins, counted, det = 0, 0, []
    for s in scenes:
        best = _gmean_by(runs_in(scenes[s], "method"), ADAPTIVE_METHODS + ("uniform",))
        oidn = _gmean([r.get("speedup") for r in runs_in(scenes[s], "peer") if r["name"] == "oidn"])
        if best and oidn:
            counted += 1
            wins += best[1] >= oidn
            det.append(f"{s}: best {best[0]} {best[1]:.2f}x vs OIDN {oidn:.2f}x")
    out.append({"target": "the best method >= OIDN's speed-up on at least half of the scenes",
                "met": (wins * 2 >= counted) if counted else None,
                "detail": det + [f"{wins} of {counted} scenes"]})

    # 3. estimated maps within 1.2x of the oracle's relMSE
    ratios, det = {}, []
    for s, d in scenes.items():
        ok = {(r["name"], r["budget"]): r for r in d["runs"] if r.get("status") == "ok"}
        for (n, b), r in ok.items():
            o = ok.get(("oracle-" + n, b))
            if r["kind"] == "method" and o is not None and o["relmse"] > 0:
                ratios.setdefault(n, []).append(r["relmse"] / o["relmse"])
    for n, v in ratios.items():
        det.append(f"{n}: relMSE / oracle's geometric mean {_gmean(v):.2f}, worst {max(v):.2f} "
                   f"({len(v)} runs)")
    out.append({"target": "estimated maps within 1.2x of the oracle's relMSE",
                "met": all(_gmean(v) <= 1.2 for v in ratios.values()) if ratios else None,
                "detail": det})

    # 4. reconstruction per megapixel vs OIDN; 5. memory
    sc = res.get("scaling") or {}
    rows = sorted((r for r in sc.get("rows", []) if "methods" in r),
                  key=lambda r: r["width"] * r["height"])
    det4, det5, met4, met5 = [], [], None, None
    if rows:
        met4 = True
        for m, bound in (("awr", 1.0), ("lp", 1.0), ("rhf", 2.0)):
            # the largest size where both the method and OIDN were timed
            row = next((r for r in reversed(rows) if "seconds_per_mp" in r["methods"].get(m, {})
                        and "seconds_per_mp" in r.get("oidn", {})), None)
            if row is None:
                errs = [r["methods"].get(m, {}).get("error") for r in rows if m in r["methods"]]
                errs = [e for e in errs if e]
                det4.append(f"{m}: not measured ({errs[0] if errs else 'not in this run'})")
                met4 = False if errs else met4
                continue
            v, oidn = row["methods"][m], row["oidn"]["seconds_per_mp"]
            ok = v["seconds_per_mp"] <= bound * oidn
            met4 &= ok
            det4.append(f"{m}: {v['seconds_per_mp']:.2f} s/MP vs OIDN {oidn:.2f} s/MP "
                        f"({v['seconds_per_mp'] / oidn:.2f}x, bound {bound:g}x) at "
                        f"{row['width']}x{row['height']}: {'met' if ok else 'NOT met'}")
            skipped = [r for r in rows if "skipped" in r["methods"].get(m, {})]
            if skipped:
                det4[-1] += f"; skipped at {skipped[-1]['width']}x{skipped[-1]['height']} (" \
                            f"{skipped[-1]['methods'][m]['skipped']})"
        met5 = True
        for m in dict.fromkeys(k for r in rows for k in r["methods"]):
            row = next((r for r in reversed(rows) if "bytes_per_pixel" in r["methods"].get(m, {})), None)
            if row is None:
                continue
            v = row["methods"][m]
            ok = v["bytes_per_pixel"] <= 400
            met5 &= ok
            det5.append(f"{m}: {v['bytes_per_pixel']:.0f} B/px working memory (+ "
                        f"{v['input_bytes_per_pixel']:.0f} B/px input buffers) at "
                        f"{row['width']}x{row['height']}: {'met' if ok else 'NOT met'}")
    out.append({"target": "reconstruction per megapixel <= OIDN's for awr and lp, <= 2x for rhf",
                "met": met4, "detail": det4 or ["no scaling section in this run"]})
    out.append({"target": "memory <= 400 bytes per pixel (reconstruct's peak traced memory)",
                "met": met5, "detail": det5 or ["no scaling section in this run"]})
    return out


def runs_in(scene_res, kind):
    """The successful runs of one kind (method, oracle, peer) of a scene."""
    return [r for r in scene_res.get("runs", []) if r.get("status") == "ok" and r["kind"] == kind]


def _gmean_by(runs, names):
    """(name, geometric-mean speed-up) of the best of ``names`` among ``runs``."""
    best = None
    for n in names:
        g = _gmean([r.get("speedup") for r in runs if r["name"] == n])
        if g and (best is None or g > best[1]):
            best = (n, g)
    return best


def summary_rows(res) -> list:
    """One row per scene x method/peer: speed-up and relMSE per budget."""
    rows = []
    for s, d in res["scenes"].items():
        if d.get("status") != "ok":
            rows.append({"scene": s, "name": "(scene failed)", "error": d.get("error")})
            continue
        names = list(dict.fromkeys(r["name"] for r in d["runs"]))
        for n in names:
            row = {"scene": s, "name": n, "speedup": {}, "relmse": {}, "seconds": {}, "errors": {}}
            for r in d["runs"]:
                if r["name"] != n:
                    continue
                b = str(r["budget"])
                if r.get("status") == "ok":
                    row["speedup"][b] = r.get("speedup")
                    row["relmse"][b] = r["relmse"]
                    row["seconds"][b] = r["seconds"]["total"]
                else:
                    row["errors"][b] = r.get("error")
            rows.append(row)
    return rows
