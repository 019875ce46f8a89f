"""Render farms on Dask distributed: region tasks and frames on worker processes.

One frame's region tasks (``--workers N`` or ``--scheduler ADDRESS``): the
controller runs the one loop, ``core.pipeline.AdaptiveRun``, with a
:class:`DaskExecutor`, whose ``render_many(tasks)`` sends an iteration's
``RegionTask``s to the workers and yields their buffers in task order, so the
loop merges exactly as with the local ``CyclesExecutor`` and the image is
identical (same seed, same tasks).

Each worker keeps one bpy session (:class:`WorkerSession`, installed by the
worker plugin :class:`BlendFilePlugin`): the .blend is saved once by the
controller as a copy named by its SHA-256 next to the outputs, every worker
checks that hash before opening it, and keeps it open with persistent data on
between tasks.  A task is a pure function of the task and the file, so a task
whose worker died is simply run again on another (Dask reschedules it).

Frame ranges (:class:`FarmFramesJob`): frames spread over workers, one Dask
task per chain; with ``--temporal reproject|lp`` a chain's frames stay in
order on one worker (chains split at camera cuts or every ``--chain-length``
frames, said in the log).

Security: a Dask scheduler runs whatever a client sends it, and a worker runs
whatever the scheduler sends.  ``--workers N`` binds the scheduler and its
workers to 127.0.0.1 (no dashboard); ``--scheduler`` refuses an unencrypted
address that is not on this machine and takes Dask's TLS settings from a file
(``--dask-security FILE``, see :func:`load_security` and docs/farm.md).

``distributed`` is optional: nothing here imports it before a farm is asked
for, so the extension loads without it.
"""
from __future__ import annotations

import contextlib
import dataclasses
import importlib
import ipaddress
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import uuid
from urllib.parse import urlsplit

import numpy as np

from ..core.io import file_sha256
from . import farm_job

LOOPBACK = "127.0.0.1"
PACKAGE = __name__.rsplit(".operators.", 1)[0]  # "cycles_adaptive" or "bl_ext.<repo>.cycles_adaptive"
ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WORKER_START_SECONDS = 180.0  # a cold worker imports bpy and distributed (seconds here)


class FarmError(Exception):
    """The farm failed (no scheduler, workers lost, bad settings); one line, exit 1.
    ``lost``: the scheduler or the workers are gone (not an error of a task)."""

    def __init__(self, message: str, lost: bool = False):
        super().__init__(message)
        self.lost = bool(lost)


# ------------------------------------------------------------------ settings
@dataclasses.dataclass(frozen=True)
class FarmSettings:
    """Where region tasks and frames run: ``workers`` local processes or an
    existing cluster at ``scheduler``; ``security``: Dask TLS settings file."""

    workers: int = 0
    scheduler: str = ""
    security: str = ""
    chain_length: int = 0


def add_render_arguments(p) -> None:
    """The farm flags of ``render`` (and ``--skip-existing`` for frame ranges)."""
    g = p.add_argument_group("farm (Dask distributed; see docs/farm.md)")
    g.add_argument("--workers", type=int, metavar="N", help="render on N local worker processes "
                   "(a Dask cluster bound to 127.0.0.1)")
    g.add_argument("--scheduler", metavar="ADDRESS", help="render on an existing Dask cluster, "
                   "tls://HOST:PORT (tcp:// only on this machine: an unsecured scheduler runs any "
                   "code sent to it)")
    g.add_argument("--dask-security", metavar="FILE", help="Dask TLS settings (YAML in Dask's "
                   "distributed.comm layout: CA, certificate and key files)")
    g.add_argument("--chain-length", type=int, metavar="N", default=0, help="frame ranges with "
                   "--temporal on a farm: a chain of frames rendered in order on one worker ends "
                   "at a camera cut or after N frames (default 0: at camera cuts only)")
    p.add_argument("--skip-existing", action="store_true", help="frame ranges: keep frames whose "
                   "output exists and render only the missing ones (with --resume, checkpointed "
                   "frames continue)")


def settings_from_args(args) -> FarmSettings | None:
    """FarmSettings from the flags, None without ``--workers``/``--scheduler``;
    ValueError (one line) for bad or unsafe combinations."""
    workers = getattr(args, "workers", None)
    scheduler = getattr(args, "scheduler", None)
    security = getattr(args, "dask_security", None)
    chain = int(getattr(args, "chain_length", 0) or 0)
    if chain < 0:
        raise ValueError("--chain-length must be >= 0")
    if workers is None and not scheduler:
        if security:
            raise ValueError("--dask-security needs --workers or --scheduler")
        return None
    if workers is not None and scheduler:
        raise ValueError("give --workers or --scheduler, not both")
    if workers is not None and workers < 1:
        raise ValueError("--workers must be at least 1")
    if security and not os.path.isfile(security):
        raise ValueError(f"--dask-security {security}: no such file")
    if scheduler:
        check_scheduler_address(scheduler, bool(security))
    return FarmSettings(workers or 0, scheduler or "", security or "", chain)


def check_scheduler_address(address: str, secured: bool) -> None:
    """Refuse what would let others run code here: an unencrypted address off
    this machine (ValueError, one line).  ``tls://`` needs ``secured``."""
    parts = urlsplit(address if "://" in address else "tcp://" + address)
    if parts.scheme not in ("tcp", "tls") or not parts.hostname or not parts.port:
        raise ValueError(f"--scheduler {address!r}: expected tls://HOST:PORT or tcp://HOST:PORT")
    if parts.scheme == "tls" and not secured:
        raise ValueError(f"--scheduler {address}: tls:// needs --dask-security FILE (certificates)")
    if parts.scheme == "tcp" and secured:
        raise ValueError(f"--scheduler {address}: with --dask-security use tls://")
    if parts.scheme == "tcp" and not _is_loopback(parts.hostname):
        raise ValueError(f"--scheduler {address} is unencrypted and unauthenticated: whoever reaches "
                         "it runs any code on the workers and this machine; use tls:// with "
                         "--dask-security FILE (docs/farm.md)")


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def load_security(path: str, role: str = "client"):
    """``distributed.security.Security`` from a YAML (or JSON) file in Dask's
    configuration layout::

        distributed:
          comm:
            require-encryption: true
            tls:
              ca-file: ca.pem
              client: {cert: client.pem, key: client-key.pem}
              worker: {cert: worker.pem, key: worker-key.pem}

    Relative file names are relative to the settings file.  ``role``
    (``client`` for the controller, ``worker``, ``scheduler``) must have a
    certificate and key; ValueError (one line) otherwise.  Encryption is always
    required.
    """
    import yaml  # a dependency of dask
    try:
        with open(path, encoding="utf-8") as f:
            cfg = yaml.safe_load(f) or {}
        tls = cfg["distributed"]["comm"]["tls"]
    except (OSError, yaml.YAMLError, KeyError, TypeError) as exc:
        raise ValueError(f"--dask-security {path}: not Dask TLS settings "
                         f"(distributed.comm.tls: {type(exc).__name__})") from None
    folder = os.path.dirname(os.path.abspath(path))
    resolve = lambda p: p if p is None or os.path.isabs(p) else os.path.join(folder, p)
    kw = {"tls_ca_file": resolve(tls.get("ca-file"))}
    for r in ("client", "worker", "scheduler"):
        sub = tls.get(r) or {}
        kw[f"tls_{r}_cert"] = resolve(sub.get("cert"))
        kw[f"tls_{r}_key"] = resolve(sub.get("key"))
    if not kw["tls_ca_file"] or not kw[f"tls_{role}_cert"]:
        raise ValueError(f"--dask-security {path}: needs tls.ca-file and tls.{role}.cert "
                         f"(and .key)")
    for k, v in kw.items():
        if v and not os.path.isfile(v):
            raise ValueError(f"--dask-security {path}: {k[4:].replace('_', ' ')} {v}: no such file")
    from distributed.security import Security
    return Security(require_encryption=True, **{k: v for k, v in kw.items() if v})


# ------------------------------------------------------------------ the farm
class Farm:
    """A Dask client for one command, with the local cluster it started.

    ``--workers N``: an in-process scheduler on 127.0.0.1 and N worker
    processes running :func:`run_worker` (the Python of this bpy module, or
    this Blender with ``-b``), each one thread and one bpy session, bound to
    127.0.0.1.  ``--scheduler``: a client of that cluster.  Use as a context
    manager; leaving it closes what it started and removes the shared .blend
    copies.
    """

    def __init__(self, settings: FarmSettings, log=print, connect_timeout: float = 30.0):
        self.settings = settings
        self.connect_timeout = connect_timeout  # reaching (and re-reaching) the scheduler
        self.log = log
        self.client = None
        self.cluster = None
        self.procs: list = []
        self.tmpdir = tempfile.mkdtemp(prefix="cycles-adaptive-farm-")
        self.shares: dict = {}
        self.plugins: list = []
        self.token = uuid.uuid4().hex[:12]

    # ------------------------------------------------------------ lifecycle
    def __enter__(self):
        try:
            self.start()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def start(self) -> None:
        try:
            import distributed
        except ImportError:
            raise FarmError("the farm needs Dask: pip install -r requirements-farm.txt "
                            "(into Blender's Python for blender -c; docs/farm.md)") from None
        s = self.settings
        security = load_security(s.security, "client") if s.security else None
        if s.workers:
            protocol = "tls://" if security else "tcp://"
            self.cluster = distributed.LocalCluster(
                n_workers=0, processes=False, host=LOOPBACK, scheduler_port=0, dashboard_address=None,
                protocol=protocol, security=security, silence_logs=40,
                scheduler_kwargs={"dashboard": False, "dashboard_address": f"{LOOPBACK}:0"})
            self.client = distributed.Client(self.cluster, security=security, timeout=self.connect_timeout)
            for i in range(s.workers):
                self.procs.append(self._spawn_worker(self.cluster.scheduler_address, f"local-{i}"))
            self._wait_for_workers(s.workers)
            self.log(f"farm: {s.workers} local worker process{'es' if s.workers != 1 else ''} "
                     f"on {self.cluster.scheduler_address}")
        else:
            try:
                self.client = distributed.Client(s.scheduler, security=security,
                                                 timeout=self.connect_timeout)
            except (OSError, TimeoutError) as exc:
                raise FarmError(f"cannot reach the Dask scheduler {s.scheduler}: {exc}") from None
            n = len(self.client.scheduler_info().get("workers", {}))
            self.log(f"farm: scheduler {s.scheduler}, {n} worker{'s' if n != 1 else ''}")

    def close(self) -> None:
        for name in self.plugins:
            try:
                self.client.unregister_worker_plugin(name)
            except Exception:  # workers or scheduler already gone
                pass
        self.plugins.clear()
        if self.client is not None:
            self.client.close(timeout=10)
        if self.cluster is not None:
            self.cluster.close(timeout=10)
        for p in self.procs:
            if p.poll() is None:
                p.terminate()
        for p in self.procs:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        for path in self.shares.values():
            with contextlib.suppress(OSError):
                os.unlink(path)
        self.shares.clear()
        shutil.rmtree(self.tmpdir, ignore_errors=True)

    def _spawn_worker(self, address: str, name: str):
        log = open(os.path.join(self.tmpdir, f"{name}.log"), "wb")
        code = worker_bootstrap(address, self.settings.security, LOOPBACK, name)
        cmd = worker_command(code)
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        try:
            return subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    env=env)
        finally:
            log.close()

    def _wait_for_workers(self, n: int) -> None:
        t_end = time.monotonic() + WORKER_START_SECONDS
        while time.monotonic() < t_end:
            if len(self.client.scheduler_info(n_workers=-1).get("workers", {})) >= n:
                return
            dead = [i for i, p in enumerate(self.procs) if p.poll() is not None]
            if dead:
                raise FarmError(f"worker process {dead[0]} exited with code "
                                f"{self.procs[dead[0]].returncode}: {self.worker_log_tail(dead[0])}")
            time.sleep(0.1)
        raise FarmError(f"{n} workers did not start within {WORKER_START_SECONDS:.0f} s")

    def worker_log_tail(self, i: int) -> str:
        try:
            with open(os.path.join(self.tmpdir, f"local-{i}.log"), encoding="utf-8", errors="replace") as f:
                lines = [ln.strip() for ln in f if ln.strip()]
        except OSError:
            return "no log"
        return lines[-1] if lines else "no output"

    @property
    def n_workers(self) -> int:
        return len(self.client.scheduler_info(n_workers=-1).get("workers", {}))

    # ---------------------------------------------------------------- files
    def share(self, scene, folder: str | None = None) -> dict:
        """Save the current .blend (with the command's in-memory changes) as a
        copy named by its SHA-256 in ``folder`` (default: a temporary folder,
        enough for local workers; on a farm: the output folder, which the
        nodes share) and install it on every worker (:class:`BlendFilePlugin`,
        also on workers that join later).  Returns the session spec tasks
        carry (``sha``, ``path``); a file already shared is reused."""
        import bpy
        from ..addon.executor import quiet_stdout
        folder = os.path.abspath(folder or self.tmpdir)
        tmp = os.path.join(folder, f".cycles-adaptive-{self.token}.tmp.blend")
        with quiet_stdout():  # "Info: Saved copy as ..."
            bpy.ops.wm.save_as_mainfile(filepath=tmp, copy=True, relative_remap=True)
        sha = file_digest(tmp)
        if (folder, sha) in self.shares:
            os.unlink(tmp)
            return dict(sha=sha, path=self.shares[folder, sha])
        path = os.path.join(folder, f".cycles-adaptive-{sha[:16]}.blend")
        os.replace(tmp, path)
        self.shares[folder, sha] = path
        name = f"cycles-adaptive-blend-{sha[:16]}"
        try:
            self.client.register_plugin(__getattr__("BlendFilePlugin")(sha, path), name=name)
        except Exception as exc:
            raise FarmError(f"workers could not install {path}: {_one_line(exc)}") from None
        self.plugins.append(name)
        return dict(sha=sha, path=path)

    # ------------------------------------------------------------ executors
    def executor_factory(self, out: str | None = None):
        """A callable with ``CyclesExecutor``'s signature ``(scene,
        view_layer, features=(), seed=None)`` returning a :class:`DaskExecutor`
        (what ``RenderJob`` builds its executor with)."""
        folder = None if self.settings.workers else os.path.dirname(os.path.abspath(out or "."))

        def make(scene, view_layer, features=(), seed=None):
            return DaskExecutor(self, scene, view_layer, features, seed, folder)
        return make


def executor_for(farm: Farm | None, out: str | None = None):
    """The executor factory RenderJob uses on ``farm``; None without one
    (RenderJob then uses ``CyclesExecutor``)."""
    return None if farm is None else farm.executor_factory(out)


def open_farm(args, log=print):
    """``Farm`` for the command's flags (a context manager), or a null
    context yielding None when neither ``--workers`` nor ``--scheduler``."""
    settings = settings_from_args(args)
    return contextlib.nullcontext() if settings is None else Farm(settings, log=log)


def worker_command(code: str) -> list:
    """The command line of one local worker process running ``code``: this
    Python when bpy is a module (``bpy.app.binary_path`` is empty), else this
    Blender in the background."""
    blender = ""
    if "bpy" in sys.modules:
        blender = sys.modules["bpy"].app.binary_path
    if blender:
        return [blender, "-b", "--factory-startup", "--python-exit-code", "1", "--python-expr", code]
    return [sys.executable, "-c", code]


def worker_bootstrap(address: str, security: str, host: str | None, name: str) -> str:
    """Python source of a worker process: import this package under this
    process's name (so pickled references resolve), then :func:`run_worker`."""
    return (
        "import importlib, importlib.util, os, sys\n"
        f"name, root = {PACKAGE!r}, {ROOT!r}\n"
        "if name not in sys.modules:\n"
        "    spec = importlib.util.spec_from_file_location(name, os.path.join(root, '__init__.py'),\n"
        "                                                  submodule_search_locations=[root])\n"
        "    mod = importlib.util.module_from_spec(spec)\n"
        "    sys.modules[name] = mod\n"
        "    spec.loader.exec_module(mod)\n"
        "farm = importlib.import_module(name + '.operators.farm')\n"
        f"sys.exit(farm.run_worker({address!r}, {security or None!r}, {host!r}, {name!r}))\n")


# ------------------------------------------------------------ the executor
class DaskExecutor:
    """The executor interface of ``core.pipeline`` over Dask workers.

    A local ``CyclesExecutor`` (configured, never rendering) gives the domain,
    size, camera and preview; ``render_many`` sends the tasks of an iteration
    to the workers at once and yields ``(color, features)`` in task order.
    Buffers travel as float32 where that is exact and are restored to float64,
    so the merge sees exactly what a local render gives.
    """

    def __init__(self, farm: Farm, scene, view_layer, features=(), seed=None, folder=None):
        from ..addon.executor import CyclesExecutor
        self.farm = farm
        self.local = CyclesExecutor(scene, view_layer, features, seed=seed)
        self.scene, self.view_layer = scene, view_layer
        self.features, self.seed = self.local.features, seed
        self.size = self.local.size
        self.folder = folder
        self.spec = None
        self.batches = 0
        self.token = uuid.uuid4().hex[:12]
        self.renders = 0

    domain = property(lambda self: self.local.domain)
    full_w = property(lambda self: self.local.full_w)
    full_h = property(lambda self: self.local.full_h)
    user_crop = property(lambda self: self.local.user_crop)

    def __enter__(self):
        share = self.farm.share(self.scene, self.folder)  # before the scene is configured
        self.spec = dict(share, scene=self.scene.name, view_layer=self.view_layer.name,
                         features=list(self.features), seed=self.seed)
        self.local.__enter__()
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def close(self) -> None:
        self.local.close()

    def camera_info(self, frame: int) -> dict:
        return self.local.camera_info(frame)

    def write_preview(self, rgba, path: str) -> None:
        self.local.write_preview(rgba, path)

    def render(self, task):
        return next(iter(self.render_many([task])))

    def render_many(self, tasks):
        """Submit every task, then yield each result in task order.

        Tasks are cut into tiles (:func:`tile_task`) so that an iteration of a
        few large renders still spreads over every worker; a border render's
        pixels do not depend on the border (tested: identical values), so the
        reassembled task is exactly the task rendered whole.  Tiles go to Dask
        in contiguous chunks of about equal cost (:func:`chunk_tasks`,
        ``CHUNKS_PER_WORKER`` per worker), so the scheduler's per-task overhead
        is paid per chunk; a chunk whose worker died runs again elsewhere."""
        tasks = list(tasks)
        if not tasks:
            return
        self.batches += 1
        client = self.farm.client
        try:
            n_chunks = CHUNKS_PER_WORKER * max(1, self.farm.n_workers)
            target = sum(task_cost(t) for t in tasks) / n_chunks
            pieces = [(i, tile) for i, t in enumerate(tasks) for tile in tile_task(t, target)]
            chunks = chunk_tasks([tile for _, tile in pieces], n_chunks)
            n = len(chunks)
            keys = [f"cycles-adaptive-region-{self.token}-{self.batches}-{i}" for i in range(n)]
            futures = client.map(remote_call(), [__name__] * n, ["render_regions"] * n, [self.spec] * n,
                                 [[task_tuple(t) for t in c] for c in chunks], key=keys, retries=0)
        except Exception as exc:
            raise _farm_error(self.farm, exc) from None
        try:
            owners = iter(pieces)
            current, color, feats = None, None, None
            for fut in futures:
                for tile_color, tile_feats in self._result(fut):
                    i, tile = next(owners)
                    if i != current:
                        if current is not None:
                            yield color, feats
                        current, task = i, tasks[i]
                        shape = (task.height, task.width)
                        color = np.zeros(shape + tile_color.shape[2:])
                        feats = {k: np.zeros(shape + v.shape[2:]) for k, v in tile_feats.items()}
                    y0, x0 = tile.y0 - task.y0, tile.x0 - task.x0
                    color[y0:y0 + tile.height, x0:x0 + tile.width] = restore(tile_color)
                    for k, v in tile_feats.items():
                        feats[k][y0:y0 + tile.height, x0:x0 + tile.width] = restore(v)
                    self.renders += 1
            if current is not None:
                yield color, feats
        finally:
            _cancel_pending(client, futures)

    @property
    def map_parts(self) -> int:
        """Bands a method's map is split into (:meth:`run_jobs`): one per worker."""
        return max(1, int(self.farm.n_workers))

    def run_jobs(self, module: str, name: str, jobs: list, local_fallback: bool = False) -> list:
        """``module.name(job)`` for each job on the workers (LP's bands of a
        sample map or of the final fit, ``core.lp.fit_band``: pure functions
        of their inputs, so a job whose worker died runs again elsewhere);
        results in job order.  With ``local_fallback`` (the final
        reconstruction: no render follows) a lost farm (the scheduler gone,
        workers that kept dying) does not fail the frame: the jobs are
        computed here, one line in the log, the same bits."""
        try:
            return self._run_jobs(module, name, jobs)
        except FarmError as exc:
            if not (local_fallback and exc.lost):
                raise
            why = str(exc).split("; ")[0]
        self.farm.log(f"farm: {why}; computing the {len(jobs)} {name} jobs on this machine")
        fn = getattr(importlib.import_module(module), name)
        return [fn(job) for job in jobs]

    def _run_jobs(self, module: str, name: str, jobs: list) -> list:
        client = self.farm.client
        self.batches += 1
        try:
            futures = [client.submit(remote_call(), module, name, job, pure=False, retries=0,
                                     key=f"cycles-adaptive-map-{self.token}-{self.batches}-{i}")
                       for i, job in enumerate(jobs)]
        except Exception as exc:
            raise _farm_error(self.farm, exc) from None
        try:
            return [self._result(f) for f in futures]
        finally:
            _cancel_pending(client, futures)

    def _result(self, fut):
        try:
            next(completed(self.farm, [fut]))
            results = fut.result()
        except FarmError:
            raise
        except Exception as exc:
            if _is_task_error(exc):
                raise
            raise _farm_error(self.farm, exc) from None
        fut.release()
        return results


KEEP = "the checkpoint of the last iteration is kept: rerun with --resume"
POLL_S = 2.0  # how often a wait on the farm checks that the scheduler is still there


def completed(farm: Farm, futures):
    """Yield ``futures`` as they finish (done, failed or cancelled), checking
    every ``POLL_S`` that the client still reaches the scheduler.

    Why: a future whose scheduler died is not always told so (its
    ``result()`` can wait for ever); a client that has not been connected for
    longer than ``farm.connect_timeout`` (its own reconnection window) or that
    closed is a lost farm: :class:`FarmError` with ``lost=True``."""
    from distributed import wait
    pending = list(futures)
    away_since = None
    while pending:
        try:
            done, rest = wait(pending, timeout=POLL_S, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done, rest = [], pending
        for fut in done:
            yield fut
        pending = list(rest)
        if done or not pending:
            away_since = None
            continue
        status = str(getattr(farm.client, "status", "running"))
        if status == "running":
            away_since = None
            continue
        now = time.monotonic()
        away_since = now if away_since is None else away_since
        if status in ("closed", "closing") or now - away_since > farm.connect_timeout:
            where = farm.settings.scheduler or "the local cluster"
            raise FarmError(f"lost the Dask scheduler ({where}): the client is {status}; {KEEP} on a new cluster",
                            lost=True)


def _cancel_pending(client, futures) -> None:
    """Cancel the futures not done yet (a batch left early: an error or a stop)."""
    pending = [f for f in futures if not f.done()]
    if pending:
        with contextlib.suppress(Exception):
            client.cancel(pending)


CHUNKS_PER_WORKER = 4  # chunks of an iteration per worker: balance against per-chunk overhead
MIN_TILE = 32  # smallest tile side in pixels: a render's fixed cost is ~1024 pixel-samples here


def task_cost(task) -> float:
    """Cost of a render in pixel-samples, the planner's fixed cost included."""
    from ..core.regions import DEFAULT_TASK_COST
    return task.pixels * task.samples + DEFAULT_TASK_COST


def tile_task(task, max_cost: float) -> list:
    """``task`` as a grid of tiles (same samples, frame, offset) of cost at
    most about ``max_cost``, none narrower than ``MIN_TILE`` pixels unless the
    task is; they cover the task's rectangle exactly once, row by row."""
    from ..core.regions import RegionTask
    n = int(np.ceil(task_cost(task) / max(max_cost, 1.0)))
    nx = max(1, min(task.width // MIN_TILE, int(round(np.sqrt(n * task.width / task.height)))))
    ny = max(1, min(task.height // MIN_TILE, int(np.ceil(n / nx))))
    xs = [task.x0 + (task.width * i) // nx for i in range(nx + 1)]
    ys = [task.y0 + (task.height * j) // ny for j in range(ny + 1)]
    return [RegionTask(xs[i], ys[j], xs[i + 1], ys[j + 1], task.samples, frame=task.frame, offset=task.offset)
            for j in range(ny) for i in range(nx)]


def chunk_tasks(tasks, n: int) -> list:
    """Split ``tasks`` (in order) into at most ``n`` contiguous chunks of about
    equal cost (:func:`task_cost`), none empty."""
    if not tasks:
        return []
    cost = np.cumsum([task_cost(t) for t in tasks], dtype=np.float64)
    n = max(1, min(int(n), len(tasks)))
    bounds = np.searchsorted(cost, cost[-1] * np.arange(1, n) / n, side="left") + 1
    edges = [0, *sorted(set(int(min(max(b, 1), len(tasks))) for b in bounds)), len(tasks)]
    return [tasks[i:j] for i, j in zip(edges[:-1], edges[1:]) if j > i]


def _remote(module, name, *args):
    """On a worker: ``module.name(*args)``."""
    import importlib
    return getattr(importlib.import_module(module), name)(*args)


def remote_call():
    """:func:`_remote` as a function pickled by value (a copy that is no
    attribute of this module): the Dask scheduler unpickles the task graph, and
    this way it needs only the standard library, not this package (which the
    workers import by its name)."""
    import types
    return types.FunctionType(_remote.__code__, {"__builtins__": __builtins__}, "_remote")


def task_tuple(task) -> tuple:
    return (int(task.x0), int(task.y0), int(task.x1), int(task.y1), int(task.samples), int(task.frame),
            int(task.offset))


def compact(a):
    """float64 array -> float32 when that is exact (Cycles' passes are
    float32), else unchanged: half the bytes on the wire, same values."""
    a = np.asarray(a)
    if a.dtype == np.float64:
        f = a.astype(np.float32)
        if np.array_equal(f.astype(np.float64), a, equal_nan=True):
            return f
    return a


def restore(a):
    return np.asarray(a, np.float64)


def _is_task_error(exc) -> bool:
    """An input error raised by the task itself on a worker (bad scene, missing
    pass, unreadable file): passed on as it is, a one-line error of the CLI."""
    names = {c.__name__ for c in type(exc).__mro__}
    return bool(names & {"SceneError", "JobError", "ImageFileError", "StorageError"})


LOST = {"FutureCancelledError", "CancelledError", "CommClosedError", "ClosedClientError", "StreamClosedError"}


def _farm_error(farm: Farm, exc) -> FarmError:
    """One line for a farm failure: workers that kept dying, the scheduler
    lost, or another error of a task on a worker."""
    names = {c.__name__ for c in type(exc).__mro__}
    if "KilledWorker" in names:
        return FarmError(f"a region task was on several workers that died ({_one_line(exc)}); {KEEP}", lost=True)
    if names & LOST or isinstance(exc, (OSError, TimeoutError)):
        where = farm.settings.scheduler or "the local cluster"
        return FarmError(f"lost the Dask scheduler ({where}): {_one_line(exc)}; {KEEP} on a new cluster",
                         lost=True)
    return FarmError(f"a task failed on a worker: {_one_line(exc)}")


def _one_line(exc) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}".rstrip(": ")


file_digest = file_sha256  # the content hash every worker checks the .blend against


# ------------------------------------------------------------ worker side
class WorkerSession:
    """The one bpy session of a worker process: the .blend files installed by
    :class:`BlendFilePlugin` (sha -> path), the file open now and a
    ``CyclesExecutor`` kept entered between tasks (persistent data on), so a
    worker syncs the scene once, not per task.  Runs on the worker's single
    task thread."""

    def __init__(self):
        self.files: dict = {}
        self.sha = None
        self.key = None
        self.executor = None
        self.address = ""  # of the worker, set by the plugin

    def add(self, sha: str, path: str) -> None:
        got = file_digest(path) if os.path.isfile(path) else None
        if got != sha:
            raise FarmError(f"{path}: {'missing on this worker' if got is None else 'content differs'} "
                            f"(expected sha256 {sha[:16]}...); the nodes must share the output folder")
        self.files[sha] = path

    def forget(self, sha: str) -> None:
        """Drop ``sha`` (called off the main thread: bpy is left alone; the
        next task that needs another file releases this one)."""
        self.files.pop(sha, None)

    def open(self, sha: str) -> None:
        """Open the file ``sha`` unless it is open (hash checked again)."""
        import bpy
        if self.sha == sha:
            return
        self.release()
        path = self.files.get(sha)
        if path is None:
            raise FarmError(f"file {sha[:16]}... is not installed on this worker")
        self.add(sha, path)
        bpy.ops.wm.open_mainfile(filepath=path, load_ui=False)
        self.sha = sha

    def scene(self, spec):
        import bpy
        self.open(spec["sha"])
        scene = bpy.data.scenes.get(spec["scene"])
        if scene is None:
            raise FarmError(f"no scene {spec['scene']!r} in {self.files[spec['sha']]}")
        vl = scene.view_layers.get(spec["view_layer"])
        if vl is None:
            raise FarmError(f"no view layer {spec['view_layer']!r} in scene {scene.name!r}")
        return scene, vl

    def region_executor(self, spec):
        from ..addon.executor import CyclesExecutor
        key = (spec["sha"], spec["scene"], spec["view_layer"], tuple(spec["features"]), spec["seed"])
        if key != self.key or self.executor is None:
            scene, vl = self.scene(spec)
            self.release()
            ex = CyclesExecutor(scene, vl, tuple(spec["features"]), seed=spec["seed"])
            ex.__enter__()
            self.executor, self.key = ex, key
        return self.executor

    def release(self) -> None:
        if self.executor is not None:
            self.executor.close()
        self.executor, self.key = None, None


_SESSION: WorkerSession | None = None


def session() -> WorkerSession:
    global _SESSION
    if _SESSION is None:
        _SESSION = WorkerSession()
    return _SESSION


def render_regions(spec: dict, tasks: list) -> list:
    """Worker task: render RegionTasks (tuples, :func:`task_tuple`) of the file
    ``spec['sha']`` in order; ``(color, features)`` each, float32 where exact
    (:func:`compact`)."""
    from ..core.regions import RegionTask
    ex = session().region_executor(spec)
    out = []
    for task in tasks:
        color, feats = ex.render(RegionTask(*task))
        out.append((compact(color), {k: compact(v) for k, v in feats.items()}))
    return out


def _plugin_class():
    """The worker plugin class, made on first use so that importing this
    module never imports ``distributed`` (module ``__getattr__`` below gives it
    its module-level name, which pickling by reference needs)."""
    from distributed.diagnostics.plugin import WorkerPlugin

    class BlendFilePlugin(WorkerPlugin):
        """Installs one content-hashed .blend on each worker (present and
        future ones): checks that the worker runs one task at a time (one bpy
        session) and that the file at ``path`` has the SHA-256 ``sha``."""

        def __init__(self, sha: str, path: str):
            self.sha, self.path = sha, path

        def setup(self, worker):
            if worker.state.nthreads != 1:
                raise FarmError(f"worker {worker.address} runs {worker.state.nthreads} threads; a bpy "
                                "session needs --nthreads 1")
            session().add(self.sha, self.path)
            session().address = worker.address

        def teardown(self, worker):
            session().forget(self.sha)

    BlendFilePlugin.__module__ = __name__
    BlendFilePlugin.__qualname__ = "BlendFilePlugin"
    return BlendFilePlugin


def __getattr__(name):
    """``BlendFilePlugin``, made (once) when first asked for."""
    if name == "BlendFilePlugin":
        if "BlendFilePlugin" not in globals():
            globals()["BlendFilePlugin"] = _plugin_class()
        return globals()["BlendFilePlugin"]
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class MainThreadExecutor:
    """A ``concurrent.futures`` executor whose work runs on the thread that
    calls :meth:`serve` (the process's main thread), one item at a time.

    bpy must be driven from the main thread (``wm.open_mainfile`` from another
    thread never returns), so a worker's event loop runs on a second thread
    and hands its tasks here.
    """

    def __init__(self):
        import queue
        self.queue = queue.Queue()

    def submit(self, fn, *args, **kwargs):
        from concurrent.futures import Future
        fut = Future()
        self.queue.put((fut, fn, args, kwargs))
        return fut

    def map(self, fn, *iterables, **kw):  # Executor interface; Dask only submits
        return [self.submit(fn, *a).result() for a in zip(*iterables)]

    def shutdown(self, wait: bool = True, cancel_futures: bool = False) -> None:
        self.queue.put(None)

    def serve(self) -> None:
        """Run submitted work until :meth:`shutdown`."""
        while True:
            item = self.queue.get()
            if item is None:
                return
            fut, fn, args, kwargs = item
            if not fut.set_running_or_notify_cancel():
                continue
            try:
                fut.set_result(fn(*args, **kwargs))
            except BaseException as exc:  # handed to the scheduler as the task's error
                fut.set_exception(exc)


def run_worker(address: str, security: str | None = None, host: str | None = None,
               name: str | None = None, death_timeout: float = 60.0) -> int:
    """Run a Dask worker in this process until its scheduler goes: its event
    loop on a second thread, its tasks on this (main) thread through
    :class:`MainThreadExecutor`, one at a time (one bpy session); no dashboard,
    and its HTTP server on ``host`` (127.0.0.1 for local workers).  Imports
    bpy first, so the first task does not pay for it."""
    import asyncio
    import threading
    import bpy  # noqa: F401  (warm: the first task renders at once)
    from distributed import Worker
    sec = load_security(security, "worker") if security else None
    executor = MainThreadExecutor()
    failed: list = []

    async def main():
        async with Worker(address, nthreads=1, host=host, name=name, security=sec, dashboard=False,
                          dashboard_address=f"{host}:0" if host else None, executor=executor,
                          death_timeout=death_timeout, memory_limit=0) as w:
            await w.finished()

    def loop():
        try:
            asyncio.run(main())
        except BaseException as exc:
            failed.append(exc)
        finally:
            executor.shutdown()

    t = threading.Thread(target=loop, name="dask-worker-loop", daemon=True)
    t.start()
    executor.serve()
    t.join()
    if failed:
        print(f"error: farm worker: {_one_line(failed[0])}", file=sys.stderr)
        return 1
    return 0


class WorkerCommand:
    """``farm-worker ADDRESS``: this Blender (or bpy Python) as a Dask worker
    of the farm, for render nodes (``blender -b -c cycles_adaptive farm-worker
    tls://HOST:PORT --dask-security FILE``)."""

    NAME = "farm-worker"
    HELP = "run a Dask worker for --scheduler renders (one bpy session, one task at a time)"

    @staticmethod
    def add_arguments(p) -> None:
        p.add_argument("address", help="the scheduler, tls://HOST:PORT (tcp:// only on this machine)")
        p.add_argument("--dask-security", metavar="FILE", help="Dask TLS settings with a worker "
                       "certificate (see render --dask-security)")
        p.add_argument("--listen", metavar="HOST", default=None, help="interface to listen on "
                       "(default: the one that reaches the scheduler)")
        p.add_argument("--name", default=None, help="worker name (default: host and port)")

    @staticmethod
    def main(args) -> int:
        check_scheduler_address(args.address, bool(args.dask_security))
        return run_worker(args.address, args.dask_security, args.listen, args.name)


WORKER = WorkerCommand


# ---------------------------------------------------------- frames on a farm
def options_dict(options) -> dict:
    d = dataclasses.asdict(options)
    d["features"] = list(d["features"])
    return json.loads(json.dumps(d, default=str))


def render_chain(spec: dict, job: dict, runs: list) -> dict:
    """Worker task: render one chain of frames (a list of ``farm_job.Run``)
    in order with ``FramesJob`` on this worker's session; per-frame summaries,
    exit codes and one-line errors."""
    from ..core.pipeline import Options
    from .job import FramesJob
    s = session()
    s.release()  # FramesJob configures the scene itself, per frame
    scene, vl = s.scene(spec)
    opts = dict(job["options"])
    opts["features"] = tuple(opts["features"])
    options = Options(**opts)
    codes, errors, summaries = {}, {}, []

    def make(frames, resume):
        return FramesJob(scene, vl, options, job["out_pattern"], frames,
                         reference_pattern=job["reference_pattern"], temporal=job["temporal"],
                         reproject_params=job["reproject_params"], temporal_params=job["temporal_params"],
                         history_params=job.get("history_params", {}), overwrite=job["overwrite"], resume=resume, preview=job["preview"],
                         exr_depth=job.get("exr_depth", "scene"), exr_contents=job.get("exr_contents", "full"),
                         seed_mode=job.get("seed_mode", "auto"))
    for step in farm_job.drive([[farm_job.Run(tuple(r[0]), bool(r[1])) for r in runs]], make, codes, errors):
        if isinstance(step, dict):
            summaries.append(json.loads(json.dumps(step, default=float)))
    return {"summaries": summaries, "codes": codes, "errors": errors, "worker": s.address}


class FarmFramesJob:
    """A frame range on the farm, with ``FramesJob``'s interface (``steps``
    yielding Progress and one summary dict per frame, ``finish``,
    ``summary``).  Frames are planned from the files (``farm_job.plan_frames``:
    skipped, resumed, rendered), split into chains (``farm_job.chains``) and
    sent one Dask task per chain; a chain's frames render in order on one
    worker, which writes their outputs (the output folder must be shared)."""

    def __init__(self, farm: Farm, scene, view_layer, options, out_pattern: str, frames: list,
                 reference_pattern: str | None = None, temporal: str = "none", reproject_params=None,
                 temporal_params=None, history_params=None, skip_existing: bool = False,
                 overwrite: bool = False, resume: bool = False, preview: bool = True, chain_length: int | None = None,
                 exr_depth: str = "scene", exr_contents: str = "full", seed_mode: str = "auto"):
        from .job import frame_path
        self.farm, self.scene, self.view_layer = farm, scene, view_layer
        self.options, self.frames, self.temporal = options, list(frames), temporal
        self.out_pattern = os.path.abspath(out_pattern)
        self.plans = farm_job.plan_frames(self.frames, lambda f: frame_path(self.out_pattern, f),
                                          skip_existing, resume, overwrite)
        self.cuts = camera_cuts(scene) if temporal != "none" else []
        length = farm.settings.chain_length if chain_length is None else chain_length
        self.chain_list = farm_job.chains(self.frames, temporal, self.cuts, length)
        self.chain_length = length
        self.runs = farm_job.frame_runs(self.plans, self.chain_list)
        self.job = {"options": options_dict(options), "out_pattern": self.out_pattern,
                    "reference_pattern": os.path.abspath(reference_pattern) if reference_pattern else None,
                    "temporal": temporal, "reproject_params": dict(reproject_params or {}),
                    "temporal_params": dict(temporal_params or {}),
                    "history_params": dict(history_params or {}), "overwrite": bool(overwrite),
                    "preview": bool(preview), "exr_depth": exr_depth, "exr_contents": exr_contents,
                    "seed_mode": seed_mode}
        self.codes = {p.frame: farm_job.SKIPPED for p in self.plans if p.action == "skip"}
        self.errors: dict = {}
        self.summaries: list = []
        self.run = None  # no local run (the operator's stepper reads it)

    def steps(self):
        from ..core.pipeline import Progress
        n = len(self.frames)
        if self.temporal != "none":
            yield Progress("plan", 0, 0.0, farm_job.describe_chains(self.chain_list, self.cuts,
                                                                    self.chain_length))
        skipped = [p.frame for p in self.plans if p.action == "skip"]
        if skipped:
            yield Progress("plan", 0, 0.0, farm_job.skipped_message(skipped))
        todo = [runs for runs in self.runs if runs]
        if not todo:
            return
        spec = dict(self.farm.share(self.scene, os.path.dirname(self.out_pattern)), scene=self.scene.name,
                    view_layer=self.view_layer.name)
        client = self.farm.client
        futures = []
        for runs in todo:
            first = runs[0].frames[0]
            futures.append(client.submit(remote_call(), __name__, "render_chain", spec, self.job,
                                         [[list(r.frames), r.resume] for r in runs],
                                         key=f"cycles-adaptive-frames-{self.farm.token}-{first}"))
        done = len(skipped)
        try:
            for fut in completed(self.farm, futures):
                try:
                    res = fut.result()
                except FarmError:
                    raise
                except Exception as exc:
                    raise _farm_error(self.farm, exc) from None
                self.codes.update({int(k): v for k, v in res["codes"].items()})
                self.errors.update({int(k): v for k, v in res["errors"].items()})
                for s in res["summaries"]:
                    self.summaries.append(s)
                    done += 1
                    yield s
                for f, msg in sorted((int(k), v) for k, v in res["errors"].items()):
                    yield Progress("plan", 0, done / n, f"frame {f} failed on {res['worker']}: {msg}")
                frames = farm_job.frames_text(int(k) for k in res["codes"])
                yield Progress("plan", 0, done / n, f"frames {frames} done on {res['worker']}")
        finally:
            with contextlib.suppress(Exception):
                client.cancel([f for f in futures if not f.done()])

    def finish(self, partial: bool = False) -> dict:
        """The range summary (workers write their own frames; a cancel here
        cancels the chains not yet done)."""
        return self.summary()

    def summary(self) -> dict:
        return farm_job.range_summary(self.summaries, self.codes, self.errors, self.options.method,
                                      self.temporal)


def camera_cuts(scene) -> list:
    """Frames of ``scene`` where a timeline marker switches the camera."""
    return farm_job.camera_cuts([(m.frame, m.camera.name if m.camera else None)
                                 for m in scene.timeline_markers])
