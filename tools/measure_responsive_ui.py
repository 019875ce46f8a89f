"""Esc latency and main-thread blocking of the stepped UI path at W x H with a
synthetic executor (numpy renders, no Cycles):
python tools/measure_responsive_ui.py METHOD W H [cancel|profile|full].
``cancel``: Esc during an adaptation with the outputs on a writer thread (as
the modal operator runs it): how long cancel() blocks, the longest timer tick
until the files are complete, and the former synchronous write for comparison."""
import os, sys, threading, time
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path[:0] = [ROOT, os.path.join(ROOT, "tests"), os.path.join(ROOT, "tests", "core")]
from launch import load_package; load_package()
import numpy as np, bpy
from blend_util import build_scene
import importlib.util as _u
_sp = _u.spec_from_file_location("core_conftest", os.path.join(ROOT, "tests", "core", "conftest.py")); _m = _u.module_from_spec(_sp); _sp.loader.exec_module(_m)
FakeExecutor = _m.FakeExecutor
from cycles_adaptive.core import methods
from cycles_adaptive.core.buffers import FEATURE_CHANNELS
from cycles_adaptive.core.pipeline import Options
from cycles_adaptive.operators.job import RenderJob
from cycles_adaptive.operators.stepper import Stepper, start_writer

method, W, H = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
mode = sys.argv[4] if len(sys.argv) > 4 else "cancel"
import os
if os.environ.get("SWITCH"): sys.setswitchinterval(float(os.environ["SWITCH"]))

class Synth(FakeExecutor):
    def __init__(self, scene, vl, passes, seed=None):
        yy, xx = np.mgrid[0:H, 0:W] / max(H, W)
        truth = np.stack([0.2 + xx, 0.3 + 0.5 * yy, 0.5 + 0.2 * np.sin(20 * xx)], -1)
        feats = {f: np.ones((H, W, FEATURE_CHANNELS.get(f, 3))) * 0.5 for f in passes if f != "alpha"}
        super().__init__(truth, feats)
        self.domain, self.full_w, self.full_h, self.user_crop = (0, 0, W, H), W, H, False
    def __enter__(self): return self
    def __exit__(self, *a): return False
    def camera_info(self, frame): return {}

scene = build_scene(16, 16)
opts = Options(method=method, spp=4, initial_spp=2, subsets=2, iterations=2, frame=1)
os.makedirs("/tmp/ui", exist_ok=True)
job = RenderJob(scene, bpy.context.view_layer, opts, f"/tmp/ui/out_{method}_{mode}.exr", overwrite=True,
                executor_factory=Synth)
threads = []
def start(fn):
    t = threading.Thread(target=fn, daemon=True); t.start(); threads.append(t)
writers = []
def start_w(fn):
    writers.append(start_writer(fn))
st = Stepper(job, slice_seconds=0.05, start=start, start_write=start_w)
blocks = []  # (seconds, stage) of each step() call
while True:
    t0 = time.perf_counter(); ended = st.step(); dt = time.perf_counter() - t0
    blocks.append((dt, st.stage))
    if mode == "profile" and st.pending is not None:
        threads[-1].join(); st.gen.close()
        import cProfile, pstats
        pr = cProfile.Profile(); pr.enable(); job.finish(partial=True, reconstruct=False); pr.disable()
        pstats.Stats(pr).sort_stats("cumulative").print_stats(18); break
    if mode == "cancel" and st.pending is not None and st.stage == "adapt":
        polls = []
        for _ in range(20):
            t0 = time.perf_counter(); st.step(); polls.append(time.perf_counter() - t0)
        t0 = time.perf_counter(); st.cancel(); esc = time.perf_counter() - t0
        busy = threads[-1].is_alive()
        ticks = []
        while True:  # the modal's timer: a step() every 10 ms until the files are complete
            t1 = time.perf_counter(); ended = st.step(); ticks.append(time.perf_counter() - t1)
            if ended:
                break
            time.sleep(0.01)
        written = time.perf_counter() - t0
        s = st.summary
        print(f"{method} {W}x{H}: step() while adapting: max {max(polls)*1e3:.3f} ms; "
              f"Esc (cancel) returned in {esc:.3f} s (adaptation still running: {busy}); "
              f"files complete {written:.2f} s after Esc, longest timer tick meanwhile {max(ticks):.3f} s "
              f"({len(ticks)} ticks); reconstructed={s['reconstructed']} spp={s['spp_mean']:.2f}")
        t0 = time.perf_counter(); threads[-1].join(); print(f"  abandoned work finished {time.perf_counter()-t0:.1f} s later")
        from cycles_adaptive.addon.display import show_result
        res, run = job.result, job.run
        alpha = run.buffers.features["alpha"].mean if "alpha" in run.buffers.features else None
        t0 = time.perf_counter(); show_result(res.image, run.buffers.n, res.error, alpha)
        print(f"  then on the main thread, the result shown in the Image Editor (show_result): {time.perf_counter()-t0:.2f} s")
        t0 = time.perf_counter(); job._output = job._written = None; job.finish(partial=True, reconstruct=False)
        print(f"  before (Esc wrote inline on the main thread), with no worker running: {time.perf_counter()-t0:.2f} s")
        break
    if ended:
        by = {}
        for dt, stg in blocks: by[stg] = max(by.get(stg, 0), dt)
        print(f"{method} {W}x{H} full stepped run: longest step() per stage (s):",
              {k: round(v, 3) for k, v in by.items()}, f"summary total {st.summary['total_seconds']:.1f} s",
              f"adapt {st.summary['adapt_seconds']:.1f} s, reconstruct {st.summary['reconstruct_seconds']:.1f} s")
        break
    if not st.pending:
        threads and threads[-1].join(0)
    time.sleep(0.01)  # the timer's interval
