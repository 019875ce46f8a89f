"""Dask farm (operators/farm.py): a run on worker processes gives exactly the
local image; a worker killed mid-task and a lost scheduler lose nothing; the
local cluster listens on 127.0.0.1 only; TLS keeps strangers out; frame ranges
spread over workers with temporal chains kept whole.  Real Cycles renders of
tiny scenes on real worker processes (each test a few seconds to ~40 s; the
scheduler-loss test waits 3 s for the client to give up)."""
import argparse
import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

bpy = pytest.importorskip("bpy")
import cloudpickle  # noqa: E402  (a dependency of distributed)
import distributed  # noqa: E402
import psutil  # noqa: E402  (a dependency of distributed)
from distributed.diagnostics.plugin import WorkerPlugin  # noqa: E402

from blend_util import build_scene  # noqa: E402

from cycles_adaptive.addon.executor import CyclesExecutor  # noqa: E402
from cycles_adaptive.core import io as imageio  # noqa: E402
from cycles_adaptive.core import methods  # noqa: E402
from cycles_adaptive.core.pipeline import AdaptiveRun, Options  # noqa: E402
from cycles_adaptive.core.regions import RegionTask  # noqa: E402
from cycles_adaptive.operators import farm  # noqa: E402
from cycles_adaptive.operators.job import FramesJob, frame_path  # noqa: E402

W, H = 96, 64  # large enough that the executor cuts tasks into tiles (MIN_TILE 32)
QUIET = dict(log=lambda *a: None)


def _opts(**kw):
    base = dict(method="lp", spp=6, initial_spp=2, subsets=2, iterations=2, seed=3, task_cost=64, frame=1)
    base.update(kw)
    return Options(**base)


def _features(opts):
    return tuple(methods.get(opts.method).PASSES)


def _run(executor, opts, checkpoint=None, resume_from=None, on_progress=None):
    """AdaptiveRun to the end on ``executor``: (Combined RGB, Samples)."""
    with executor:
        run = AdaptiveRun(executor, opts, checkpoint=checkpoint)
        if resume_from:
            run.load_checkpoint(resume_from)
        for p in run.steps():
            if on_progress:
                on_progress(run, p)
        result = run.reconstruct()
    return result.image, run.buffers.n.copy(), run


_LOCAL = {}


def _local(opts):
    """The local CyclesExecutor run of the test scene (cached per options)."""
    key = json.dumps(farm.options_dict(opts), sort_keys=True)
    if key not in _LOCAL:
        scene = build_scene(W, H)
        ex = CyclesExecutor(scene, bpy.context.view_layer, _features(opts), seed=opts.seed)
        image, n, _ = _run(ex, opts)
        _LOCAL[key] = (image, n)
    return _LOCAL[key]


def _dask(f, opts, **kw):
    scene = build_scene(W, H)
    make = f.executor_factory()
    return _run(make(scene, bpy.context.view_layer, _features(opts), seed=opts.seed), opts, **kw)


@pytest.fixture(scope="module")
def farm2():
    with farm.Farm(farm.FarmSettings(workers=2), **QUIET) as f:
        yield f


def _batches(stream, kind) -> dict:
    """{batch: set of indices} of a task stream's keys cycles-adaptive-KIND-token-batch-index."""
    out = {}
    for t in stream.data:
        key = str(t["key"])
        if key.startswith(f"cycles-adaptive-{kind}-"):
            batch, index = key.split("-")[-2:]
            out.setdefault(int(batch), set()).add(int(index))
    return out


# ------------------------------------------------------------ identical images
def test_two_workers_render_exactly_the_local_image(farm2):
    opts = _opts()
    ref_image, ref_n = _local(opts)
    with distributed.get_task_stream(farm2.client) as ts:
        image, n, run = _dask(farm2, opts)
    assert np.abs(image - ref_image).max() == 0.0  # Combined
    assert np.abs(n - ref_n).max() == 0.0            # Samples
    assert run.iteration >= 2 and run.tasks_rendered > 4
    assert run.executor.renders > run.tasks_rendered  # tasks were cut into tiles
    workers = {t["worker"] for t in ts.data if "region" in str(t["key"])}
    assert len(workers) == 2  # both workers rendered region tasks
    maps, renders = _batches(ts, "map"), _batches(ts, "region")
    # lp's maps (one before each planning round) and its final fit: two bands each, on the workers
    assert len(maps) >= run.iteration + 1 and all(bands == {0, 1} for bands in maps.values())
    assert max(maps) > max(renders)  # the last batch of bands is the final fit, after every render


def test_buffers_travel_as_float32_only_where_exact():
    a = np.float32(np.random.default_rng(0).random((4, 4, 3))).astype(np.float64)
    assert farm.compact(a).dtype == np.float32 and np.array_equal(farm.restore(farm.compact(a)), a)
    b = a + np.float32(0.1).astype(np.float64) * 1e-9  # a float64 sum of passes (glossy dir + ind)
    assert farm.compact(b).dtype == np.float64 and np.array_equal(farm.restore(farm.compact(b)), b)


# ---------------------------------------------------------------- faults
class KillOnce(WorkerPlugin):
    """Test fault: the first worker to start its ``nth`` region task kills its
    own process with SIGKILL (once per marker file)."""

    def __init__(self, marker, nth=3):
        self.marker, self.nth, self.seen = marker, nth, 0

    def transition(self, key, start, finish, **kw):
        if finish != "executing" or "cycles-adaptive-region" not in str(key):
            return
        self.seen += 1
        if self.seen == self.nth:
            try:
                fd = os.open(self.marker, os.O_CREAT | os.O_EXCL | os.O_WRONLY)
            except FileExistsError:
                return
            os.write(fd, str(os.getpid()).encode())
            os.close(fd)
            os.kill(os.getpid(), signal.SIGKILL)


cloudpickle.register_pickle_by_value(sys.modules[__name__])  # workers cannot import this test module


def test_a_worker_killed_mid_task_loses_nothing(tmp_path):
    opts = _opts()
    ref_image, ref_n = _local(opts)
    marker = str(tmp_path / "killed")
    with farm.Farm(farm.FarmSettings(workers=2), **QUIET) as f:
        pids = set(f.client.run(os.getpid).values())
        f.client.register_plugin(KillOnce(marker), name="kill-once")
        image, n, run = _dask(f, opts)
        killed = int(open(marker).read())
        assert killed in pids
        assert [p.poll() for p in f.procs if p.pid == killed] == [-signal.SIGKILL]
        assert f.n_workers == 1  # the task went to the other worker
    assert np.abs(image - ref_image).max() == 0.0
    assert np.abs(n - ref_n).max() == 0.0


def _scheduler_process(tmp_path):
    sf = str(tmp_path / "scheduler.json")
    proc = subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", "0", "--no-dashboard", "--scheduler-file", sf],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    t_end = time.monotonic() + 60
    while time.monotonic() < t_end:
        try:
            return proc, json.load(open(sf))["address"]
        except (OSError, ValueError, KeyError):
            time.sleep(0.1)
    proc.kill()
    raise AssertionError("the Dask scheduler did not start")


@contextlib.contextmanager
def _standalone_cluster(tmp_path, workers, log=QUIET["log"]):
    """(scheduler process, Farm) of a standalone scheduler with ``workers``
    ``farm-worker`` processes; everything killed on exit."""
    sched, address = _scheduler_process(tmp_path)
    procs = [subprocess.Popen(farm.worker_command(farm.worker_bootstrap(address, None, farm.LOOPBACK, f"w{i}")),
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL) for i in range(workers)]
    try:
        with farm.Farm(farm.FarmSettings(scheduler=address), connect_timeout=3.0, log=log) as f:
            f.client.wait_for_workers(workers, timeout=120)
            yield sched, f
    finally:
        sched.kill()
        for proc in procs:
            proc.kill()
            proc.wait()


def test_a_lost_scheduler_stops_with_one_line_and_resume_finishes_exactly(tmp_path, farm2):
    """A standalone scheduler (it never imports this package) with a
    ``farm-worker`` process; the scheduler is killed after iteration 1: one
    error line naming --resume; the checkpoint resumed on another cluster gives
    the uninterrupted local image."""
    opts = _opts()
    ref_image, ref_n = _local(opts)
    ckpt = str(tmp_path / "run.checkpoint.npz")
    with _standalone_cluster(tmp_path, 1) as (sched, f):
        def kill_after_first_iteration(run, p):
            if p.stage == "checkpoint" and p.iteration == 1:
                sched.kill()
        with pytest.raises(farm.FarmError) as err:
            _dask(f, opts, checkpoint=ckpt, on_progress=kill_after_first_iteration)
    msg = str(err.value)
    assert "\n" not in msg and "lost the Dask scheduler" in msg and "--resume" in msg
    image, n, run = _dask(farm2, opts, checkpoint=ckpt, resume_from=ckpt)
    assert np.abs(image - ref_image).max() == 0.0
    assert np.abs(n - ref_n).max() == 0.0


def test_a_wait_on_a_silent_lost_scheduler_ends_in_a_farm_error(farm2, monkeypatch):
    """A future that is never told its scheduler died (a client reconnecting
    for longer than its window, or closed) ends the wait with a lost-farm
    error instead of waiting for ever; a connected client keeps waiting and
    yields each future as it finishes."""
    from types import SimpleNamespace
    monkeypatch.setattr(farm, "POLL_S", 0.1)
    quick = farm2.client.submit(farm.remote_call(), "time", "sleep", 0.3, pure=False)
    assert list(farm.completed(farm2, [quick])) == [quick]
    # needs a resource no worker has: pending for ever, and no worker is kept busy
    stuck = farm2.client.submit(farm.remote_call(), "time", "sleep", 0, pure=False, resources={"none": 1})
    try:
        for status in ("connecting", "closed"):
            gone = SimpleNamespace(client=SimpleNamespace(status=status), connect_timeout=0.5,
                                   settings=farm2.settings)
            with pytest.raises(farm.FarmError) as err:
                list(farm.completed(gone, [stuck]))
            assert err.value.lost and "lost the Dask scheduler" in str(err.value) and "--resume" in str(err.value)
    finally:
        stuck.cancel()


def test_a_scheduler_lost_after_the_last_render_still_gives_the_local_image(tmp_path):
    """lp's final fit goes to the workers in bands; the scheduler is killed
    after the last render: the fit is computed on the controller instead (one
    log line), and the image is the local run's."""
    opts = _opts()
    ref_image, ref_n = _local(opts)
    lines = []
    with _standalone_cluster(tmp_path, 2, log=lines.append) as (sched, f):
        scene = build_scene(W, H)
        ex = f.executor_factory()(scene, bpy.context.view_layer, _features(opts), seed=opts.seed)
        with ex:
            run = AdaptiveRun(ex, opts)
            for _ in run.steps():
                pass
        assert ex.map_parts == 2 and ex.batches >= 2  # the maps went to the workers
        sched.kill()
        sched.wait()
        result = run.reconstruct()
    assert np.abs(result.image - ref_image).max() == 0.0
    assert np.abs(run.buffers.n - ref_n).max() == 0.0
    fallback = [line for line in lines if "on this machine" in line]
    assert len(fallback) == 1 and "lost the Dask scheduler" in fallback[0] and "fit_band" in fallback[0]


def test_a_worker_refuses_a_file_whose_content_changed(tmp_path):
    path = tmp_path / "a.blend"
    path.write_bytes(b"BLENDER-v404 original")
    sha = farm.file_digest(str(path))
    s = farm.WorkerSession()
    s.add(sha, str(path))
    path.write_bytes(b"BLENDER-v404 tampered")
    with pytest.raises(farm.FarmError, match="content differs"):
        s.open(sha)
    with pytest.raises(farm.FarmError, match="missing"):
        s.add(sha, str(tmp_path / "gone.blend"))


# --------------------------------------------------------------- security
def test_local_workers_listen_on_loopback_only(farm2):
    info = farm2.client.scheduler_info(n_workers=-1)
    assert info["address"].startswith("tcp://127.0.0.1:")
    assert all(a.startswith("tcp://127.0.0.1:") for a in info["workers"])
    pids = [os.getpid(), *farm2.client.run(os.getpid).values()]  # the scheduler runs in this process
    for pid in pids:
        listening = [c.laddr for c in psutil.Process(pid).net_connections("inet")
                     if c.status == psutil.CONN_LISTEN]
        assert listening and all(addr.ip == "127.0.0.1" for addr in listening), listening


def _args(**kw):
    base = dict(workers=None, scheduler=None, dask_security=None, chain_length=0)
    base.update(kw)
    return argparse.Namespace(**base)


def test_unsafe_farm_settings_are_refused_with_one_line(tmp_path):
    sec = tmp_path / "sec.yaml"
    sec.write_text("distributed: {}\n")
    assert farm.settings_from_args(_args()) is None
    for kw, words in [(dict(scheduler="tcp://10.1.2.3:8786"), "unencrypted and unauthenticated"),
                      (dict(scheduler="tcp://render-head:8786"), "unencrypted"),
                      (dict(scheduler="tls://10.1.2.3:8786"), "needs --dask-security"),
                      (dict(scheduler="tcp://10.1.2.3:8786", dask_security=str(sec)), "use tls://"),
                      (dict(scheduler="10.1.2.3"), "expected tls://HOST:PORT"),
                      (dict(workers=0), "at least 1"),
                      (dict(workers=2, scheduler="tcp://127.0.0.1:8786"), "not both"),
                      (dict(dask_security=str(sec)), "needs --workers or --scheduler"),
                      (dict(workers=2, dask_security=str(tmp_path / "none.yaml")), "no such file")]:
        with pytest.raises(ValueError, match=words) as err:
            farm.settings_from_args(_args(**kw))
        assert "\n" not in str(err.value)
    assert farm.settings_from_args(_args(scheduler="tcp://127.0.0.1:8786")).scheduler
    assert farm.settings_from_args(_args(scheduler="tls://10.1.2.3:8786", dask_security=str(sec))).security
    with pytest.raises(ValueError, match="not Dask TLS settings"):
        farm.load_security(str(sec))


def _certificates(folder):
    """A CA and one certificate for the farm's parties, signed by it (openssl)."""
    folder.mkdir(exist_ok=True)
    def ssl(*args):
        subprocess.run(["openssl", *args], cwd=folder, check=True, capture_output=True)
    ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca-key.pem", "-out", "ca.pem",
        "-days", "2", "-subj", "/CN=farm-ca")
    ssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", "key.pem", "-out", "req.csr", "-subj", "/CN=farm")
    (folder / "ext.cnf").write_text("subjectAltName=IP:127.0.0.1,DNS:localhost\n")
    ssl("x509", "-req", "-in", "req.csr", "-CA", "ca.pem", "-CAkey", "ca-key.pem", "-CAcreateserial",
        "-out", "cert.pem", "-days", "2", "-extfile", "ext.cnf")
    sec = folder / "security.yaml"
    sec.write_text("distributed:\n  comm:\n    require-encryption: true\n    tls:\n      ca-file: ca.pem\n"
                   + "".join(f"      {r}: {{cert: cert.pem, key: key.pem}}\n"
                             for r in ("client", "worker", "scheduler")))
    return str(sec)


@pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command for test certificates")
def test_tls_farm_renders_and_refuses_clients_without_certificates(tmp_path):
    sec = _certificates(tmp_path)
    scene = build_scene(24, 16)
    task = RegionTask(0, 0, 24, 16, 2, frame=1, offset=0)
    with CyclesExecutor(scene, bpy.context.view_layer, ("albedo",), seed=5) as ex:
        ref_color, ref_feats = ex.render(task)
    with farm.Farm(farm.FarmSettings(workers=1, security=sec), **QUIET) as f:
        address = f.client.scheduler_info()["address"]
        assert address.startswith("tls://127.0.0.1:")
        with f.executor_factory()(scene, bpy.context.view_layer, ("albedo",), seed=5) as ex:
            color, feats = ex.render(task)
        assert np.array_equal(color, ref_color) and np.array_equal(feats["albedo"], ref_feats["albedo"])
        stranger = farm.load_security(_certificates(tmp_path / "stranger"))  # another CA
        with pytest.raises((OSError, TimeoutError)):
            distributed.Client(address, security=stranger, timeout=3)
        with pytest.raises((OSError, TimeoutError)):
            distributed.Client(address.replace("tls://", "tcp://"), timeout=3)  # plain TCP


# ------------------------------------------------------------- frame ranges
def _frames_scene():
    scene = build_scene(24, 16)
    return scene, bpy.context.view_layer


def _read(path):
    passes, _ = imageio.read_layers(path)
    return passes["Combined"], passes["Samples"]


def _local_frames(tmp, frames_runs, temporal="none", opts=None):
    """Outputs of local FramesJob runs (one per list of frames)."""
    scene, vl = _frames_scene()
    pattern = str(tmp / "f_####.exr")
    for frames in frames_runs:
        job = FramesJob(scene, vl, opts or _opts(method="var", spp=4), pattern, frames, temporal=temporal,
                        preview=False)
        for _ in job.steps():
            pass
    return pattern


def _farm_frames(f, tmp, frames, **kw):
    scene, vl = _frames_scene()
    pattern = str(tmp / "f_####.exr")
    job = farm.FarmFramesJob(f, scene, vl, kw.pop("opts", _opts(method="var", spp=4)), pattern, frames,
                             preview=False, **kw)
    log = [s.message for s in job.steps() if not isinstance(s, dict)]
    return pattern, job, log


def test_frames_spread_over_workers_match_local_frames(tmp_path, farm2):
    (tmp_path / "local").mkdir()
    (tmp_path / "farm").mkdir()
    local = _local_frames(tmp_path / "local", [[1, 2, 3]])
    pattern, job, log = _farm_frames(farm2, tmp_path / "farm", [1, 2, 3])
    summary = job.summary()
    assert summary["exit_code"] == 0 and summary["exit_summary"] == "exit codes per frame: 1-3=0"
    workers = {m.split(" on ")[-1] for m in log if m.startswith("frames ")}
    assert len(workers) == 2  # frames went to both workers
    for fr in (1, 2, 3):
        a, b = _read(frame_path(local, fr)), _read(frame_path(pattern, fr))
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])


def test_temporal_chains_stay_on_one_worker_and_match_local_chains(tmp_path, farm2):
    opts = _opts(method="var", spp=4)
    (tmp_path / "local").mkdir()
    (tmp_path / "farm").mkdir()
    local = _local_frames(tmp_path / "local", [[1, 2], [3]], temporal="reproject", opts=opts)
    pattern, job, log = _farm_frames(farm2, tmp_path / "farm", [1, 2, 3], temporal="reproject",
                                     chain_length=2, opts=opts)
    assert log[0] == "2 chains kept in order on one worker each (1-2, 3); split at every 2 frames"
    assert [m.split(" done on ")[0] for m in log if " done on " in m] in (["frames 1-2", "frames 3"],
                                                                          ["frames 3", "frames 1-2"])
    assert job.summary()["exit_code"] == 0
    for fr in (1, 2, 3):
        a, b = _read(frame_path(local, fr)), _read(frame_path(pattern, fr))
        assert np.array_equal(a[0], b[0]) and np.array_equal(a[1], b[1])
    assert _read(frame_path(pattern, 2))[0].shape == (16, 24, 4)


def test_a_requeued_range_renders_only_the_missing_frame(tmp_path, farm2):
    pattern, job, _ = _farm_frames(farm2, tmp_path, [1, 2, 3])
    before = {fr: os.stat(frame_path(pattern, fr)).st_mtime_ns for fr in (1, 3)}
    first = _read(frame_path(pattern, 2))
    os.unlink(frame_path(pattern, 2))
    with pytest.raises(ValueError, match="frame 1: .* exists; pass --skip-existing"):
        _farm_frames(farm2, tmp_path, [1, 2, 3])
    pattern, job, log = _farm_frames(farm2, tmp_path, [1, 2, 3], skip_existing=True)
    assert job.summary()["exit_summary"] == "exit codes per frame: 1=skipped 2=0 3=skipped"
    assert "skipping 2 finished frames: 1, 3" in log
    assert {fr: os.stat(frame_path(pattern, fr)).st_mtime_ns for fr in (1, 3)} == before
    again = _read(frame_path(pattern, 2))
    assert np.array_equal(first[0], again[0]) and np.array_equal(first[1], again[1])


# ------------------------------------------------------------ command line
def test_render_with_workers_flag_writes_the_local_image(tmp_path):
    """``./cycles-adaptive render --workers 2`` against a local render of the
    same .blend and seed (CLI subprocesses; ~15 s), and the refusal of an
    unsecured remote scheduler (exit 2, one line)."""
    from blend_util import save_scene
    blend = str(tmp_path / "s.blend")
    save_scene(blend, width=W, height=H)
    cli = [os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "cycles-adaptive"),
           "render", blend, "--method", "lp", "--spp", "6", "--initial-spp", "2", "--seed", "3", "--quiet"]
    env = dict(os.environ, CYCLES_ADAPTIVE_PYTHON=sys.executable)
    outs = [str(tmp_path / "local.exr"), str(tmp_path / "farm.exr")]
    for out, extra in zip(outs, ([], ["--workers", "2"])):
        r = subprocess.run([*cli, "--out", out, *extra], capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-3000:]
    (a_img, a_n), (b_img, b_n) = _read(outs[0]), _read(outs[1])
    assert np.array_equal(a_img, b_img) and np.array_equal(a_n, b_n)
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".cycles-adaptive-")]  # shared copy removed
    r = subprocess.run([*cli, "--out", str(tmp_path / "x.exr"), "--scheduler", "tcp://10.1.2.3:8786"],
                       capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 2 and r.stderr.count("\n") == 1 and "unencrypted" in r.stderr
    assert not os.path.exists(tmp_path / "x.exr")


def test_tiles_cover_a_task_exactly_once():
    for task, cost in [(RegionTask(3, 5, 203, 101, 4, frame=2, offset=7), 5000.0),
                       (RegionTask(0, 0, 40, 32, 2), 1.0), (RegionTask(0, 0, 3840, 2160, 3), 1e5),
                       (RegionTask(10, 10, 18, 90, 1), 10.0)]:
        tiles = farm.tile_task(task, cost)
        cover = np.zeros((task.y1, task.x1), int)
        for t in tiles:
            assert (t.samples, t.frame, t.offset) == (task.samples, task.frame, task.offset)
            assert min(t.width, t.height) >= min(farm.MIN_TILE, task.width, task.height)
            cover[t.y0:t.y1, t.x0:t.x1] += 1
        assert (cover[task.y0:, task.x0:] == 1).all() and cover.sum() == task.pixels
    big = RegionTask(0, 0, 3840, 2160, 3)
    assert len(farm.tile_task(big, farm.task_cost(big) / 256)) >= 256
    chunks = farm.chunk_tasks(farm.tile_task(big, farm.task_cost(big) / 256), 16)
    assert len(chunks) == 16 and sum(len(c) for c in chunks) >= 256
