"""The adaptive render loop, independent of Blender.

initial pass (K sample subsets) -> method's sample map -> region tasks ->
render + exact merge -> repeat until the budget is spent -> reconstruction.

An *executor* renders region tasks; the Cycles one lives in ``addon/executor.py``
and tests may use any object with the same two members:

``size``                       (H, W) of the image domain in pixels
``render(task) -> (color, features)``
                               color (h, w, 4) or (h, w, 3) float mean of the
                               task's samples, features a dict pass -> (h, w, C);
                               arrays the executor does not change afterwards
                               (a large task merges on a background thread
                               while the next renders)

and optionally ``render_many(tasks) -> iterator of (color, features)``, which
may render an iteration's tasks in parallel (e.g. on farm workers) but yields
the results in task order: the loop merges them in that order, so the image
does not depend on which executor rendered it; ``drop_passes(names)``, which
stops rendering feature passes that carry no information;
``render_deferred(task) -> take``, which renders now and returns a call that
gives ``render``'s result (the loop calls it on the merge's thread: reading
the passes back hides behind the next render; it must touch no Blender data);
``run_jobs(module, name, jobs, local_fallback=False) -> list`` with
``map_parts`` (int), which computes ``module.name(job)`` for each job (pure
functions of their arguments, e.g. LP's bands of rows of a sample map or of
the final fit) elsewhere, results in order; with ``local_fallback`` (the
final reconstruction, which may come after the executor's context has
exited) it computes them here when its workers are gone; and
``hold_samples_at(count)``, called before entering when every pixel of the run
ends at one known count (:func:`hold_samples`), so the renders may use a
count-tuned sampling pattern, and ``release_hold()``, called when a selecting
method's choice samples adaptively after all: the renders from then on use a
pattern whose subsets of any length merge exactly.

``AdaptiveRun.steps()`` is a generator of ``Progress`` records, so the modal
operator (a timer steps it), the batch CLI (a for loop printing lines) and the
tests share one function.  ``finish()`` reconstructs from whatever has been
rendered, so a cancel keeps every sample.

Budget accounting: ``spp`` is the mean samples per pixel of the whole run,
initial pass included.  The loop stops when fewer than 0.9 % of the budget
remains, and never plans more than what remains, so the total is within 1 %.

Task cost: the planner trades the fixed cost of one region render against the
samples spent beyond the map by rounding up to rectangles.  ``Options.task_cost``
(pixel-samples) sets it; it is a setting, not a timing measured during the run,
so a run is deterministic: the same seed and budget give the same tasks and the
same image, and a resumed run ends exactly where an uninterrupted one does.
A time limit (``Options.max_seconds``) is the exception: its rounds are sized
from the run's measured render and reconstruction seconds (``core/timeplan.py``).
"""
from __future__ import annotations

import copy
import json
import threading
import time
from dataclasses import asdict, dataclass, field, fields, replace

import numpy as np

from . import cryptomatte, maps, methods, metrics, regions, storage, timeplan, variance
from .buffers import Buffers
from .method import Method, check_ranges, consistency_guard, param, params_from_dict

TOP_UP = 3        # planning rounds the last iteration may add to spend what rounding left
MAX_BEYOND_MAP = 0.1  # most samples an iteration's plan may add beyond the map (share of its samples)
MAX_EXACT_TASKS = 64  # most renders a pixel-exact fallback plan may take
#: a task this large (256x256) merges on a background thread while the next
#: renders (Cycles releases the GIL while it renders; numpy's merge does too)
MERGE_WORK_PIXELS = 1 << 16
#: Options.render_seconds: the first subset of a run, before any render has
#: been timed, renders its first band as this share of the rows
FIRST_BANDS = 8


@dataclass
class Options:
    """Loop settings: the one declaration the CLI flags (``--initial-spp``) and
    the panel's properties are generated from (``operators/cli.py``,
    ``addon/props.py``).  Each field's metadata (:func:`core.method.param`)
    holds ``help`` (what it trades), ``min``/``max``, a human ``label``, and
    ``ui``/``cli`` (False: not shown there).  ``method``, ``frame``,
    ``params`` and ``features`` are set by the caller, not generated.
    """

    method: str = param("auto", "adaptive method: where samples go and how the image is "
                        "reconstructed (auto: chosen per scene from the first pass)",
                        label="Method", cli=False, ui=False)
    spp: float = param(16.0, "mean samples per pixel of the whole run (initial pass included); more "
                       "is slower and more accurate", 1e-6, None, label="Samples per Pixel",
                       ui_min=1.0, soft_max=4096.0)
    initial_spp: int = param(4, "samples per pixel of the first, uniform pass; more gives a better "
                             "first error estimate and leaves less budget to adapt", 1, None,
                             label="Initial Samples", soft_max=64)
    #: 4 by default: 3 degrees of freedom halve the relative spread of the
    #: variance estimate compared with the 2-buffer scheme (1 dof) at the cost
    #: of two more full-frame renders, which take ~10 ms each once synced
    subsets: int = param(4, "sample subsets of the first pass (variance estimate with subsets-1 "
                         "degrees of freedom); more: steadier estimate, a few more full-frame renders",
                         1, 64, label="Subsets")
    iterations: int = param(4, "adaptive iterations after the first pass; more: the sample map "
                            "follows the error more closely, more per-render overhead", 1, 64,
                            label="Iterations")
    frame: int = param(0, "frame to render", label="Frame", cli=False, ui=False)
    seed: int = param(0, "Cycles seed of the run", 0, None, label="Seed")
    min_task_size: int = param(16, "smallest region render side in pixels; smaller follows the "
                               "sample map more closely, more renders", 1, None, label="Min Region Size")
    #: fixed cost of one region render in pixel-samples (see regions.plan)
    task_cost: float = param(regions.DEFAULT_TASK_COST, "fixed cost of one region render in "
                             "pixel-samples; higher merges more regions (fewer renders, samples less "
                             "adaptive)", 0.0, None, label="Region Cost")
    #: Our safeguards, not in the papers: per-pixel estimates from a few sample
    #: groups are heavy-tailed, so the map is pooled by confidence and to the
    #: planner's blocks (core/maps.py) before planning, and then capped at twice
    #: the iteration's mean: with today's maps the cap still measures better
    #: than following them (docs/notes/planner.md)
    pool_maps: bool = param(True, "pool each sample map over 3x3 pixels weighted by how many "
                            "sample groups each pixel's estimate rests on, then over the region "
                            "blocks, before planning; off follows the method's per-pixel map",
                            label="Pool Sample Maps")
    max_pixel_share: float = param(2.0, "most samples a pixel may get in one iteration, as a "
                                   "multiple of the iteration's mean (0: no cap); lower spreads "
                                   "samples more evenly, higher follows the method's map to its peaks",
                                   0.0, None, label="Max Pixel Share", soft_max=64.0)
    #: final image: core.method.consistency_guard (our safeguard, not in the papers)
    guard_z: float = param(3.0, "final image: a pixel more than this many standard errors from its "
                           "own sample mean falls back to it (0: off); lower trusts the "
                           "reconstruction less", 0.0, None, label="Consistency Guard", soft_max=10.0)
    #: planned from the run's own timings (core/timeplan.py)
    max_seconds: float = param(0.0, "wall-time limit of the run in seconds (0: none): rounds are sized "
                               "by what the run's renders cost, long renders split, and time kept for "
                               "the final reconstruction and the output's write", 0.0, None,
                               label="Time Limit", subtype="TIME_ABSOLUTE")
    #: no render longer than this (core/timeplan.py); the panel's default
    #: (ui_default) keeps Blender drawing and answering Esc between renders
    render_seconds: float = param(0.0, "longest one render should take, in seconds (0: no bound): a "
                                  "task the run's own renders predict to take longer renders as bands "
                                  "of rows, each pixel's samples in one band, so the image is the same; "
                                  "Blender redraws and answers Esc between renders, at a small cost "
                                  "per extra render", 0.0, None,
                                  label="Longest Render", subtype="TIME_ABSOLUTE", soft_max=10.0,
                                  ui_default=1.0)
    #: the loop then checks the estimate before each round and sizes the
    #: round from the fitted convergence (next_target_spp); --spp is the most it renders
    target_error: float = param(0.0, "keep sampling until the final image's estimated relMSE is "
                                "below this (0: off); the samples per pixel are then the most the "
                                "run may render, and each round renders what the error's measured "
                                "convergence predicts reaches it, at most doubling the samples "
                                "(iterations is ignored)", 0.0, None, label="Target Error", soft_max=1.0)
    #: Tabulated Sobol merges subsets of any length exactly; a count-tuned pattern
    #: (Blue Noise) only with the count held (CyclesExecutor.hold_samples_at)
    scene_pattern: bool = param(True, "a run that samples uniformly at a whole spp (uniform, oidn "
                                "without adaptive sampling, auto when it chooses uniform sampling; no "
                                "time limit or target) renders with the scene's own sampling pattern, "
                                "as plain Cycles does (Blender 4.4+); off: Tabulated Sobol, the same "
                                "noise on every Blender version",
                                label="Scene's Sampling Pattern")
    params: dict = field(default_factory=dict, metadata={"cli": False, "ui": False})
    #: extra passes to read beyond the method's own
    features: tuple = field(default=(), metadata={"cli": False, "ui": False})

    OWNER = "option"  # range errors read "option spp=-1 must be >= 1e-06"

    def __post_init__(self):
        check_ranges(self)


def option_fields(where: str) -> list:
    """The :class:`Options` fields generated for ``where`` ("cli" or "ui")."""
    return [f for f in fields(Options) if f.metadata.get(where, True)]


class Work:
    """A pure computation the loop is about to wait for (no bpy inside, unless
    ``main_thread``).

    The loop yields it in a :class:`Progress` and then calls :meth:`result`, so
    a consumer that ignores it gets the computation inline, and one that keeps a
    UI responsive may call :meth:`run` on a worker thread (numpy releases the
    GIL) and resume the loop once :attr:`done`; not where ``main_thread`` is
    True (it calls Blender: the compositor's OIDN where pyoidn is missing),
    which must run inline.  ``run`` is idempotent and thread-safe: a second
    caller waits for the first; an exception is stored and re-raised by
    :meth:`result`.
    """

    def __init__(self, fn, label: str = "", main_thread: bool = False, mutates: bool = False):
        self.fn = fn
        self.label = label
        #: the computation calls something that only runs on the main thread
        #: (Blender's own OIDN): a consumer must run it inline
        self.main_thread = bool(main_thread)
        #: the computation changes the run's buffers (a merge): a consumer that
        #: stops waiting for it (Esc) must let it end before reading them
        self.mutates = bool(mutates)
        self._lock = threading.Lock()
        self._done = threading.Event()
        self._value = None
        self._error: BaseException | None = None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    def run(self) -> None:
        with self._lock:
            if self._done.is_set():
                return
            try:
                self._value = self.fn()
            except BaseException as exc:  # handed to the caller of result()
                self._error = exc
            finally:
                self.fn = None
                self._done.set()

    def result(self):
        self.run()
        if self._error is not None:
            raise self._error
        return self._value


@dataclass
class Progress:
    """One step of the loop, for progress bars and batch log lines.  ``work``:
    the computation the loop waits for next (see :class:`Work`), or None."""

    stage: str            # "initial", "adapt", "plan", "render", "saving", "checkpoint", "done"
    iteration: int
    fraction: float       # 0..1 of the sample budget rendered
    message: str
    tasks_done: int = 0
    tasks_total: int = 0
    work: Work | None = None


@dataclass
class Prior:
    """Samples carried into a run from earlier frames (e.g. reprojected from the
    previous frame), the one way history enters the loop.

    buffers : Buffers of the run's domain, merged after the initial pass and
        counted in ``AdaptiveRun.reused``, not against the render budget.
    state : entries merged into the sampler's state before its first map
        (e.g. Schalk's Alg. 2 reads ``state["probability"]``).
    info : scalar diagnostics for the run's summary.
    """

    buffers: Buffers
    state: dict = field(default_factory=dict)
    info: dict = field(default_factory=dict)


@dataclass
class Timing:
    render: float = 0.0
    adapt: float = 0.0
    reconstruct: float = 0.0
    overhead: float = 0.0

    def total(self) -> float:
        return self.render + self.adapt + self.reconstruct + self.overhead


class AdaptiveRun:
    """State of one adaptive render of one frame."""

    def __init__(self, executor, options: Options, checkpoint: str | None = None, prior=None,
                 method: Method | None = None, started: float | None = None, view_transform=None):
        """``method``: the :class:`core.method.Method` to run (default: the
        registered method ``options.method``; wrappers such as the oracle are
        passed here).  ``prior``: optional callable ``prior(buffers) -> Prior |
        None``, called once with the initial pass's Buffers (read only) to
        give the samples carried from earlier frames (:class:`Prior`).
        ``started``: the ``time.perf_counter()`` from which ``max_seconds``
        counts (default: the first call of :meth:`steps`; a job passes its own
        start so the limit bounds its wall time, scene setup included).
        ``view_transform``: optional ``f(buffers) -> Buffers`` (pure, new
        arrays) applied to what the method reads (:attr:`view`): the frame's
        samples with earlier frames' accumulated in
        (``core.history.accumulate``), so the sampler and the reconstruction
        both count them."""
        self.executor = executor
        self.options = options
        self.method = methods.method_for(options.method, options.params) if method is None else method
        self.params = params_from_dict(self.method.Params, options.params)
        h, w = executor.size
        self.height, self.width = int(h), int(w)
        self.pixels = self.height * self.width
        self.budget = int(round(options.spp * self.pixels))
        adaptive = self.method.ADAPTIVE
        spp_int = max(1, int(np.floor(options.spp)))
        # with a target the budget is a ceiling, and with a time limit the
        # first renders measure what a render costs: every method starts small
        self.initial_spp = spp_int if not (adaptive or options.target_error > 0 or options.max_seconds > 0) \
            else min(options.initial_spp, spp_int)
        self.subsets = max(1, min(options.subsets, self.initial_spp))
        # alpha (Combined.A) rides along as a one-channel pass so nothing is lost
        self.feature_names = tuple(dict.fromkeys(tuple(self.method.PASSES) + tuple(options.features)
                                                 + ("alpha",)))
        self.buffers: Buffers | None = None
        self.next_index = np.zeros((self.height, self.width), np.int64)
        self.iteration = 0
        self.method_state: dict = {"seed": options.seed}
        self.timing = Timing()
        self.tasks_rendered = 0
        self.overshoot = 0
        self.checkpoint_path = checkpoint
        self.prior = prior
        self.reused = np.zeros((self.height, self.width))  # samples merged from ``prior``
        self._count_lock = threading.Lock()
        self._count = None  # (key, samples_rendered) while :meth:`_merge` keeps it current
        self.prior_info: dict = {}
        self.history: list = []
        self.started = started
        self.time_limited = False       # True once max_seconds stopped the sampling
        self.max_task_seconds = 0.0     # longest single task render (the limit's granularity)
        self.sampling_seconds = 0.0     # elapsed() when the sampling ended
        self.selection: dict | None = None  # what a selecting method (auto) chose, for reports
        self.dropped: tuple = ()            # feature passes found to carry no information
        self.view_transform = view_transform
        self._view = None                   # (key, Buffers) of the latest transformed view
        self.cryptomatte: dict = {}         # base -> CryptoAccumulator (merge_cryptomatte)
        self.cryptomatte_header: dict = {}  # base -> the renders' cryptomatte/<key>/ attributes
        self._cv: list = []                 # initial subsets on a selecting method's tiles
        self._initial_seconds: list = []    # render seconds of each initial subset
        self._last_render_seconds = 0.0     # the latest task's render (_count_render)
        self.target_met = False             # Options.target_error reached
        self.estimates: list = []           # (spp, estimated relMSE) at each target check
        self._result = None                 # (samples, MethodResult) of the last target check
        self._pending: Work | None = None   # the merge running in the background (_merge_steps)
        self._pending_samples = 0           # samples_rendered once it has landed
        # a time limit (core/timeplan.py): the renders' fitted cost, the final
        # reconstruction's and a round's measured or estimated seconds, and
        # what the caller sets aside for its own output (reserve_seconds)
        self.cost = timeplan.RenderCost()
        self.reserve_seconds = 0.0
        #: optional ``probe(buffers) -> seconds``: a time-limited run calls it
        #: once, after the initial pass's first subset (as a Work, pure: no
        #: bpy unless reserve_probe_main_thread), and keeps what it returns
        #: in reserve_seconds (the job: its outputs' write, compositor and
        #: preview)
        self.reserve_probe = None
        self.reserve_probe_main_thread = False
        self.reconstruct_estimate: float | None = None
        self._round_seconds: float | None = None   # a round's seconds besides its renders
        self._round_tasks = 0                      # renders of the latest round
        self._round_samples = 0                    # and its samples
        self.slices = 0                            # tasks split to fit the limit or render_seconds
        self._crop_estimate_at = None              # samples when reconstruct_estimate came from crops

    # ------------------------------------------------------------- accounting
    @property
    def samples_rendered(self) -> int:
        """Samples rendered by this run (reused samples not included).

        The loop reads it after every task (progress, the time limit), and a
        whole-frame sum each time costs ~1 ms per megapixel per task on the
        controller (a 4K frame of ~17 000 tasks: about a minute).  So the sum
        is taken once and :meth:`_merge` adds each task's samples; the count
        is taken again whenever the buffers or ``reused`` are replaced or
        changed elsewhere (reuse), and not kept while a merge is half done."""
        if self.buffers is None:
            return 0
        key = (id(self.buffers), id(self.buffers.n), id(self.reused))
        with self._count_lock:
            if self._count is not None and self._count[0] == key:
                return self._count[1]
            count = int(round(self.buffers.n.sum() - self.reused.sum()))
            pending = self._pending
            if pending is None or pending.done:  # whole buffers: keep the count
                self._count = (key, count)
            return count

    @property
    def view(self) -> Buffers:
        """The buffers as the method reads them: without the passes found to
        carry no information (:attr:`dropped`), through ``view_transform``
        (computed once per state of the samples)."""
        view = self.buffers.without(self.dropped)
        if self.view_transform is None:
            return view
        key = (id(self.buffers), float(self.buffers.n.sum()), self.dropped)
        if self._view is None or self._view[0] != key:
            self._view = (key, self.view_transform(view))
        return self._view[1]

    @property
    def remaining(self) -> int:
        return self.budget - self.samples_rendered

    def _fraction(self) -> float:
        # while a merge runs the buffers are half updated: count it as landed
        done = self._pending_samples if self._pending is not None else self.samples_rendered
        return min(1.0, done / max(self.budget, 1))

    @property
    def pending_merge(self) -> "Work | None":
        """The merge still running on a background thread (a :class:`Work`
        marked ``mutates``), or None.  The loop waits for it before it reads
        the buffers itself; a consumer that stopped the loop (Esc, Ctrl-C, an
        error) waits through :meth:`settle` or this Work's ``run`` before it
        reads them."""
        return self._pending

    def settle(self) -> None:
        """Wait for :attr:`pending_merge`, if any; its exception is raised here."""
        work, self._pending = self._pending, None
        if work is not None:
            work.result()

    def elapsed(self) -> float:
        """Seconds since the run's clock started (``started``)."""
        return 0.0 if self.started is None else time.perf_counter() - self.started

    @property
    def timed(self) -> bool:
        """The run has a time limit (``Options.max_seconds``)."""
        return self.options.max_seconds > 0

    def final_reserve(self) -> float:
        """Seconds the limit keeps for what follows the sampling: the final
        reconstruction (:attr:`reconstruct_estimate`) and the caller's output
        (:attr:`reserve_seconds`)."""
        return float(self.reconstruct_estimate or 0.0) + max(float(self.reserve_seconds), 0.0)

    def _sampling_seconds_left(self) -> float:
        """Seconds the limit still leaves for sampling: ``Options.max_seconds``
        less the elapsed time and :meth:`final_reserve`."""
        return self.options.max_seconds - self.elapsed() - self.final_reserve()

    def _time_up(self) -> bool:
        """``Options.max_seconds`` spent, less :meth:`final_reserve`: checked
        before every task, so the sampling ends within one task (one slice,
        :func:`core.timeplan.slice_tasks`) of the limit."""
        if self.timed and self._sampling_seconds_left() <= 0:
            self.time_limited = True
        return self.time_limited

    def _band_seconds(self) -> float:
        """``Options.render_seconds`` (0: off), never below twice the renders'
        fitted overhead, so that bounding a render for the UI's sake cannot
        turn it into many that mostly pay overhead."""
        if self.options.render_seconds <= 0:
            return 0.0
        return max(self.options.render_seconds, 2.0 * self.cost.fit()[0])

    def _would_overrun(self, task) -> bool:
        """A time-limited run's ``task`` is predicted (:attr:`cost`) to end
        more than a slice (``timeplan.SLICE_SHARE`` of the limit) past what
        the limit leaves for sampling: the initial pass's full-frame subsets,
        which are not sliced, stop before such a one."""
        if not self.timed or not len(self.cost):
            return False
        overrun = self.cost.predict(task.pixels * task.samples) - self._sampling_seconds_left()
        return overrun > timeplan.SLICE_SHARE * self.options.max_seconds

    def _time_cap(self, rounds: int) -> tuple:
        """``(samples, uniform)``: what the next round may render so that it
        and the ``rounds - 1`` after it fit the time left
        (``Options.max_seconds`` less :meth:`final_reserve`), each round also
        paying its adaptation, merges and checkpoint (the latest round's
        seconds besides its renders, or before any round the
        reconstruction's estimate when the sampler reads one).  Rounds are
        dropped until each renders at least as long as it adapts; when not
        even one such round fits, adapting would cost more than the samples
        it places, and the round samples uniformly with all the time left
        (``uniform`` True; only for an adaptive method)."""
        rounds = max(1, int(rounds))
        left = self._sampling_seconds_left()
        per_round = self._round_seconds
        if per_round is None:
            per_round = float(self.reconstruct_estimate or 0.0) if self.method.SAMPLER_USES_RESULT else 0.0
        # renders per sample: the latest round's, or the initial pass's
        initial_rps = len(self.cost) / max(self.samples_rendered, 1)
        if self._round_tasks and self._round_samples:
            rps = self._round_tasks / self._round_samples
        else:
            rps = initial_rps
        if self.method.ADAPTIVE and per_round > 0:
            fit = int(left // (2.0 * per_round))
            if fit < 1:
                return self.cost.samples_within(left, initial_rps), True
            rounds = min(rounds, fit)
        share = (left - rounds * per_round) / rounds
        return self.cost.samples_within(share, rps), False

    def _measure_reserves(self):
        """A time-limited run's :meth:`final_reserve`: the caller's
        ``reserve_probe`` (its output's write), once, and the final
        reconstruction's estimate (:meth:`_measure_reconstruction`; a
        selecting method's after its choice).  The initial pass calls it after
        its first subset, so the subsets that follow are planned with it, and
        the loop again after the pass: a method's cost depends on the sample
        groups it sees (LP's on one group measured 4.7x its cost on four), so
        an estimate from crops of fewer samples is measured again."""
        if not self.timed:
            return
        yield from self._settle_steps()  # the probe and the crops read the buffers
        if self.reserve_probe is not None:
            probe, buf = self.reserve_probe, self.buffers
            self.reserve_probe = None
            work = Work(lambda: probe(buf), "timing the output's write", self.reserve_probe_main_thread)
            yield Progress("adapt", 0, self._fraction(), work.label, work=work)
            self.reserve_seconds = float(work.result())
        if selects(self.method):
            return
        if self.reconstruct_estimate is None or self._crop_estimate_at not in (None, self.samples_rendered):
            self._crop_estimate_at = self.samples_rendered
            yield from self._measure_reconstruction()

    def _measure_reconstruction(self):
        """A time-limited run's estimate of the final reconstruction's
        seconds before any: the method's reconstruction of two centre crops
        (a quarter of each side, at least 64 px, and half of that), timed
        and extrapolated to the frame by the line through both
        (:func:`core.timeplan.extrapolate_seconds`: a fixed cost is not
        scaled with the pixels; the small crop runs first and pays any
        one-time set-up, which then over-estimates rather than under).  A
        small frame is its own crop, timed once, and its reconstruction is
        kept for the end.  A full reconstruction measured later replaces the
        estimate."""
        h, w = self.height, self.width
        ch, cw = min(h, max(64, h // 4)), min(w, max(64, w // 4))
        whole = (ch, cw) == (h, w)  # a small frame: its reconstruction, kept for the end
        samples = self.samples_rendered

        def crop(ch, cw):
            y0, x0 = (h - ch) // 2, (w - cw) // 2
            return self.view.crop(x0, y0, x0 + cw, y0 + ch)

        def timed(buf):
            t0 = time.perf_counter()
            result = self.method.reconstruct(buf, self.params)
            seconds = time.perf_counter() - t0
            self.timing.adapt += seconds
            return result, seconds

        def measure():
            if whole:
                result, seconds = timed(self.view)
                self._result = (samples, result)
                return seconds
            sh, sw = max(32, ch // 2), max(32, cw // 2)
            small = timed(crop(sh, sw))[1]
            large = timed(crop(ch, cw))[1]
            return timeplan.extrapolate_seconds(sh * sw, small, ch * cw, large, self.pixels)

        work = Work(measure, f"timing the reconstruction ({self.method.NAME}) on {cw}x{ch} px",
                    self.main_thread_only())
        yield Progress("adapt", 0, self._fraction(), work.label, work=work)
        self.reconstruct_estimate = work.result()

    # ------------------------------------------------------------------ steps
    def steps(self):
        """Generator of Progress; runs the loop to the end of the budget."""
        opts = self.options
        if self.started is None:
            self.started = time.perf_counter()
        if self.buffers is None:
            yield from self._initial_pass()
            if self.prior is not None:
                carried = self.prior(self.buffers)
                if carried is not None:
                    extra = carried.buffers
                    self.reused += extra.n
                    self.buffers.merge(extra)
                    self._count = None  # both changed in place: count again
                    self.method_state.update(carried.state)
                    self.prior_info = dict(carried.info)
                    yield Progress("initial", 0, self._fraction(),
                                   f"reused {int(extra.n.sum())} samples on "
                                   f"{int((extra.n > 0).sum())} pixels from the previous frame")
            yield from self._drop_uninformative()
            if selects(self.method):
                yield from self._select()
            yield from self._checkpoint()
        if not self._time_up():
            yield from self._measure_reserves()
        tol = max(1, int(0.009 * self.budget))  # the total lands within 1 % of the budget
        target = opts.target_error > 0
        while (target or self.iteration < opts.iterations) and self.remaining > tol \
                and not self._time_up():
            if target:
                self.target_met = yield from self._target_reached()
                if self.target_met:
                    break
                # to the spp the fitted convergence predicts reaches the target (next_target_spp)
                step = self._target_step()
                last = step >= self.remaining - tol
            else:
                last = self.iteration == opts.iterations - 1 or not self.method.ADAPTIVE
            entry = {"iteration": self.iteration + 1, "tasks": 0, "samples": 0, "overshoot": 0}
            if target:  # the check that planned this iteration (kept by checkpoints: resume replans alike)
                entry["target_check"] = list(self.estimates[-1])
            # the last iteration may take up to TOP_UP more planning rounds to
            # spend what rounding to rectangles left over (each a new map)
            for _ in range(1 + (TOP_UP if last else 0)):
                if self.remaining <= tol or self._time_up():
                    break
                left = max(1, opts.iterations - self.iteration)
                if target:
                    budget = self.remaining if last else step
                else:
                    budget = self.remaining if last else int(self.remaining / left)
                uniform = False
                if self.timed:  # no more than the time left holds (core/timeplan.py)
                    cap, uniform = self._time_cap(1 if (last or target) else left)
                    if uniform:
                        entry["uniform"] = True
                        yield Progress("plan", self.iteration, self._fraction(),
                                       f"iteration {self.iteration + 1}: the time left holds no adaptation "
                                       f"and the samples it would plan; sampling uniformly")
                    if cap < budget:
                        budget = cap
                    if budget < (self.pixels if uniform else self._smallest_round()):
                        self.time_limited = True
                        break
                t0, rendered_before = time.perf_counter(), self.timing.render
                samples_before = self.samples_rendered
                rendered = yield from self._round(budget, entry, uniform)
                if not uniform:  # what an adaptive round costs besides its renders, and its renders
                    self._round_seconds = time.perf_counter() - t0 - (self.timing.render - rendered_before)
                    if rendered:
                        self._round_tasks, self._round_samples = rendered, self.samples_rendered - samples_before
                if not rendered:
                    break
            self.history.append(entry)
            self.iteration += 1
            t0 = time.perf_counter()
            yield from self._checkpoint()
            if self._round_seconds is not None and not entry.get("uniform"):  # the next round pays one too
                self._round_seconds += time.perf_counter() - t0
            yield Progress("checkpoint", self.iteration, self._fraction(),
                           f"iteration {self.iteration} done, {self.samples_rendered / self.pixels:.2f} spp")
        self.sampling_seconds = self.elapsed()
        if target and not self.target_met:
            yield Progress("plan", self.iteration, self._fraction(),
                           f"target relMSE {opts.target_error:g} not reached within the budget "
                           f"({self.samples_rendered / self.pixels:.2f} spp)")
        if self.time_limited:
            yield Progress("plan", self.iteration, self._fraction(),
                           f"time limit of {opts.max_seconds:g} s reached after {self.elapsed():.2f} s")
        yield Progress("done", self.iteration, self._fraction(), "sampling done")

    def _smallest_round(self) -> int:
        """Fewest samples worth a round of a time-limited run: one sample per
        pixel for a method that samples uniformly (its rounds are whole
        sample subsets), a sixteenth of one for an adaptive one."""
        return self.pixels if not self.method.ADAPTIVE else max(1, self.pixels // 16)

    def _round(self, budget: int, entry: dict, uniform: bool = False):
        """One planning round of the current iteration: adapt (a :class:`Work`),
        plan, render, merge; adds its figures to the iteration's ``entry``.
        ``uniform``: whole sample subsets without adapting (a time limit's
        choice, :meth:`_time_cap`).  Returns the number of tasks rendered (0:
        nothing to plan)."""
        overshoot_before = self.overshoot
        if (uniform or not self.method.ADAPTIVE) and budget >= self.pixels:
            # uniform sampling after the initial pass (auto's choice, a target
            # error): whole spp as sample subsets like the initial pass, so the
            # variance estimate keeps groups of comparable size
            spp = budget // self.pixels
            tasks = subset_tasks(self.width, self.height, spp, self.subsets, self.options.frame)
            covered = np.full((self.height, self.width), spp, np.int64)
            counts = covered.copy()
        else:
            work = Work(lambda: self._adapt(budget),
                        f"iteration {self.iteration + 1}: adapting ({self.method.NAME})",
                        self.main_thread_only())
            yield Progress("adapt", self.iteration, self._fraction(), work.label, work=work)
            tasks, covered, counts = work.result()
        if not tasks:
            return 0
        n = len(tasks)
        if self.timed:  # no task longer than a slice of the limit
            tasks = timeplan.slice_tasks(tasks, self.cost, timeplan.SLICE_SHARE * self.options.max_seconds)
        before = self.next_index
        tasks, self.next_index = regions.assign_offsets(tasks, self.next_index)
        # nor than render_seconds: bands keep their task's offset, so its samples
        tasks = timeplan.band_tasks(tasks, self.cost, self._band_seconds())
        self.slices += len(tasks) - n
        yield Progress("plan", self.iteration, self._fraction(),
                       f"iteration {self.iteration + 1}: {len(tasks)} region tasks, "
                       f"{int(covered.sum())} samples", 0, len(tasks))
        done = []
        for item in self._render_tasks(tasks):
            if isinstance(item, Progress):  # a large task's merge, as a Work
                yield item
                continue
            done.append(item)
            yield Progress("render", self.iteration, self._fraction(),
                           f"iteration {self.iteration + 1}: task {len(done)}/{len(tasks)}",
                           len(done), len(tasks))
        if len(done) < len(tasks):  # stopped by the time limit: keep what was rendered
            nxt = np.array(before, np.int64, copy=True)  # each rendered task's own offset (bands too)
            for t in done:
                nxt[t.y0:t.y1, t.x0:t.x1] = t.offset + t.samples
            self.next_index = nxt
            covered = np.zeros_like(covered)
            for t in done:
                covered[t.y0:t.y1, t.x0:t.x1] += t.samples
            self.overshoot = overshoot_before + int(np.maximum(covered - counts, 0).sum())
        entry["tasks"] += len(done)
        entry["samples"] += int(covered.sum())
        entry["overshoot"] += self.overshoot - overshoot_before
        return len(done)

    def _initial_pass(self):
        tasks = subset_tasks(self.width, self.height, self.initial_spp, self.subsets, self.options.frame)
        self.buffers = Buffers.empty(self.height, self.width, self.feature_names)
        self._count = None
        meter = variance.ExponentMeter()
        # a selecting method scores candidates on crops of the separate subsets
        crops = self.method.cv_regions(self.height, self.width, self.params) if selects(self.method) else []
        self._cv = [[] for _ in crops]
        last, sizes = tasks[0], []
        for s, task in enumerate(tasks):
            if s and (self._time_up() or self._would_overrun(task)):  # one subset at least: an image
                self.time_limited = True
                break
            def measure(pieces, task=task):
                color = _stack_rows([c for c, _ in pieces])
                meter.add(color, task.samples)
                for keep, (x0, y0, x1, y1) in zip(self._cv, crops):
                    keep.append((np.array(color[y0:y1, x0:x1, :3], np.float64),
                                 {k: np.array(_stack_rows([f[k] for _, f in pieces])[y0:y1, x0:x1],
                                              np.float64)
                                  for k in pieces[0][1] if k in self.method.PASSES},
                                 task.samples))
            yield from self._render_subset(task, measure, f"initial pass: subset {s + 1}/{len(tasks)}")
            last = task
            sizes.append(task.samples)
            yield Progress("initial", 0, self._fraction(),
                           f"initial pass: subset {s + 1}/{len(tasks)} ({task.samples} spp)",
                           s + 1, len(tasks))
            if s == 0 and len(tasks) > 1:  # the subsets that follow fit what the output needs
                yield from self._measure_reserves()
        yield from self._settle_steps()
        self.next_index[:] = last.offset + last.samples
        # the sequence's stratification, measured once on the equal subsets (core/variance.py)
        work = Work(lambda: meter.exponent(self.buffers), "initial pass: measuring the noise's convergence")
        yield Progress("initial", 0, self._fraction(), work.label, work=work)
        # from here on the buffers keep their groups' sizes (the calibrated variance's Eq. 1)
        self.buffers.set_exponent(work.result(), sizes)

    def _drop_uninformative(self):
        """Feature passes the method reads that carry no information in this
        frame (:meth:`core.buffers.Buffers.constant_features`, on the initial
        pass): the method no longer reads them (:attr:`view`), and an executor
        that can (``drop_passes``) stops rendering those the run does not
        also keep for its output (``Options.features``).  Albedo stays while
        normal is read (OIDN takes the normal only with an albedo)."""
        reads = [p for p in self.method.PASSES if p in self.buffers.features]
        work = Work(lambda: self.buffers.constant_features(reads), "initial pass: finding constant passes")
        yield Progress("initial", 0, self._fraction(), work.label, work=work)
        flat = set(work.result())
        if "albedo" in flat and "normal" in reads and "normal" not in flat:
            flat.discard("albedo")
        self.dropped = tuple(p for p in reads if p in flat)
        if not self.dropped:
            return
        self._stop_rendering()
        yield Progress("initial", 0, self._fraction(),
                       f"passes without information in this frame, not read: {', '.join(self.dropped)}")

    def _stop_rendering(self) -> None:
        drop = getattr(self.executor, "drop_passes", None)  # optional member, see module notes
        unkept = [p for p in self.dropped if p not in self.options.features]
        if drop is not None and unkept:
            drop(unkept)

    def _target_reached(self):
        """Reconstruct what is rendered (a :class:`Work`) and compare its
        estimated relMSE (:func:`core.metrics.robust_relmse` of the method's
        error: the mean of the per-pixel terms with the firefly outliers
        winsorised) with ``Options.target_error``; the result is kept for the
        round's sampler, the check in :attr:`estimates`.  Returns True once
        below."""
        if not self.estimates:  # a resumed run: the checks made before its checkpoint
            self.estimates = [tuple(h["target_check"]) for h in self.history if "target_check" in h]
        samples = self.samples_rendered
        work = Work(lambda: self._timed_reconstruct(), f"iteration {self.iteration + 1}: estimating the "
                    f"error ({self.method.NAME})", self.main_thread_only())
        yield Progress("adapt", self.iteration, self._fraction(), work.label, work=work)
        result = work.result()
        self._result = (samples, result)
        est = metrics.robust_relmse(result.image, result.error)
        spp = samples / self.pixels
        self.estimates.append((spp, est))
        reached = est <= self.options.target_error
        yield Progress("adapt", self.iteration, self._fraction(),
                       f"estimated relMSE {est:.3g} at {spp:.2f} spp "
                       f"({'below' if reached else 'above'} the target {self.options.target_error:g})")
        return reached

    def _target_step(self) -> int:
        """Samples of the next round of a target-error run: up to the spp
        :func:`next_target_spp` predicts from the checks so far; whole spp
        for a method that samples uniformly (its rounds are sample subsets),
        at least one sample per pixel."""
        now = self.samples_rendered / self.pixels
        grow = max(next_target_spp(self.estimates, self.options.target_error) - now, 0.0)
        if not self.method.ADAPTIVE:
            return max(1, int(round(grow))) * self.pixels
        return max(self.pixels, int(round(grow * self.pixels)))

    def _timed_reconstruct(self):
        t0 = time.perf_counter()
        result = self.method.reconstruct(self.view, self.params, **self._spread())
        seconds = time.perf_counter() - t0
        self.timing.adapt += seconds
        if self.timed:
            self.reconstruct_estimate = seconds
            self._crop_estimate_at = None
        return result

    def _select(self):
        """Let a selecting method (``auto``) choose the method to run from the
        initial pass (a :class:`Work`); the run continues with its choice,
        default parameters, and reports it in :attr:`selection`."""
        from .auto import Context
        opts, buf = self.options, self.buffers
        # the first render of a session also builds the scene (BVH, textures):
        # the others say what a render of this frame costs
        secs = self._initial_seconds
        steady = secs[1:] if len(secs) > 1 else secs
        render_seconds = float(np.median(steady)) * len(secs) if steady else self.timing.render
        ctx = Context(spp=float(opts.spp), initial_spp=self.samples_rendered / self.pixels,
                      pixels=self.pixels, render_seconds=render_seconds, tasks=self.tasks_rendered,
                      iterations=opts.iterations, task_cost=opts.task_cost,
                      max_pixel_share=opts.max_pixel_share, min_task_size=opts.min_task_size,
                      exponent=buf.exponent, target_error=opts.target_error)
        crops = self.method.cv_regions(self.height, self.width, self.params)
        dropped = set(self.dropped)
        data = [[(c, {k: v for k, v in f.items() if k not in dropped}, n) for c, f, n in tile]
                for tile in self._cv]
        chooser, params = self.method, self.params

        def choose():
            t0 = time.perf_counter()
            var = buf.variance_of_mean().mean(axis=-1)
            lum = np.clip(buf.color.mean.mean(axis=-1), 0.0, None)
            with np.errstate(invalid="ignore", over="ignore"):
                rel_var = var / (lum * lum + 0.01)
            sel = chooser.select(crops, data, ctx, rel_var, params, self.height, self.width)
            self.timing.adapt += time.perf_counter() - t0
            return sel

        work = Work(choose, f"choosing a method ({self.method.NAME})", self.main_thread_only())
        yield Progress("adapt", 0, self._fraction(), work.label, work=work)
        sel = work.result()
        self._cv = []
        self._adopt(sel.method, sel.report, sel.params)
        yield Progress("adapt", 0, self._fraction(), f"{self.options.method}: {sel.report['chosen']} "
                       f"({sel.report['why']})")

    def main_thread_only(self) -> bool:
        """True when the method's computations may call OIDN through a
        backend that runs only on the main thread (:func:`core.oidn.needs_main_thread`)."""
        name = str(self.method.NAME)
        if not (name == "auto" or "oidn" in name):
            return False
        from . import oidn
        return oidn.needs_main_thread(getattr(self.params, "backend", "auto"))

    def _adopt(self, method, report: dict, params: dict | None = None) -> None:
        if method.ADAPTIVE:  # its pixels end at unequal counts: no held count (held_count)
            release = getattr(self.executor, "release_hold", None)  # optional member, see module notes
            if release is not None:
                release()
        self.method = method
        self.params = params_from_dict(method.Params, params or {})
        self.selection = report

    def _shaped(self, counts: np.ndarray) -> np.ndarray:
        """A method's map as the planner gets it: pooled by confidence and to
        the planner's blocks (``Options.pool_maps``, :mod:`core.maps`), then
        capped (``Options.max_pixel_share``)."""
        counts = np.asarray(counts, np.int64)
        if self.options.pool_maps and counts.sum() > 0:
            counts = maps.confidence_pool(counts, self.buffers.k - 1.0)
            counts = maps.pool_to_blocks(counts, self.options.min_task_size)
        return self._capped(counts)

    def _planned(self, counts: np.ndarray):
        """The cheapest plan at ``Options.task_cost`` whose samples beyond the
        map stay within ``MAX_BEYOND_MAP`` of its samples (:func:`core.regions.plan_within`)."""
        return regions.plan_within(counts, frame=self.options.frame, min_size=self.options.min_task_size,
                                   task_cost=self.options.task_cost, max_beyond=MAX_BEYOND_MAP)

    def _capped(self, counts: np.ndarray) -> np.ndarray:
        """Apply ``Options.max_pixel_share`` to a map (:func:`core.maps.cap_share`)."""
        return maps.cap_share(counts, self.options.max_pixel_share)

    def _render_subset(self, task, measure, label: str):
        """Render and merge one whole-frame initial subset ``task``, then
        ``measure([(color, features), ...])`` on its renders, top to bottom.
        With ``Options.render_seconds`` a subset the run's renders predict to
        take longer renders as full-width bands of rows, at most
        ``timeplan.MAX_BANDS`` (the first subset, before anything is known,
        as a first band of ``1 / FIRST_BANDS`` of the rows): each band holds the subset's samples and offset, so each
        pixel still gets one sample group of the same samples, and a
        Progress between bands lets Blender redraw and answer Esc.  The
        bands' seconds, summed, are the subset's (``_initial_seconds``)."""
        longest = self._band_seconds()
        pieces, seconds, y = [], 0.0, task.y0
        while y < task.y1:
            rows = task.y1 - y
            if longest > 0 and rows > 1:
                if len(self.cost):
                    rows = min(rows, max(timeplan.rows_within(self.cost, longest, task.width, task.samples),
                                         -(-task.height // timeplan.MAX_BANDS)))
                else:
                    rows = min(rows, -(-task.height // FIRST_BANDS))
            band = replace(task, y0=y, y1=y + rows)
            take = self._render(band)
            seconds += self._last_render_seconds
            pieces.append(take)
            y = band.y1
            done = y >= task.y1
            yield from self._merge_steps(band, take, (lambda: measure([t() for t in pieces])) if done else None)
            if not done:
                yield Progress("render", 0, self._fraction(),
                               f"{label}: rows {task.y0}-{y} of {task.y1}", y - task.y0, task.height)
        self._initial_seconds.append(seconds)

    def _render(self, task):
        """Render one task (the executor: Blender's main thread); returns
        ``take() -> (color, features)``.  A task that merges in the background
        (``MERGE_WORK_PIXELS``) is rendered through the executor's
        ``render_deferred`` where it has one, so reading its passes back
        happens in the merge, behind the next render."""
        t0 = time.perf_counter()
        defer = getattr(self.executor, "render_deferred", None)  # optional member, see module notes
        if defer is not None and task.pixels >= MERGE_WORK_PIXELS:
            take = defer(task)
        else:
            rendered = self.executor.render(task)
            take = lambda: rendered  # noqa: E731
        self._count_render(time.perf_counter() - t0, task)
        return take

    def _merge_steps(self, task, take, also=None):
        """Merge one rendered task (``take() -> (color, features)``, then
        ``also()``), after the merge before
        it has landed, so merges keep their order and the buffers their bits.
        A task of at least ``MERGE_WORK_PIXELS`` merges on a background thread
        (:attr:`pending_merge`, a :class:`Work` marked ``mutates``) while the
        loop goes on to render the next: Cycles renders with the GIL released,
        so the merge's seconds (~0.07 s per 0.6-megapixel subset) hide behind
        the render instead of adding to it.  The loop waits for it
        (:meth:`_settle_steps`) before anything of its own reads the buffers."""
        def merge():
            self._merge(task, *take())
            if also is not None:
                also()
        label = f"merging {task.x1 - task.x0}x{task.y1 - task.y0} px, {task.samples} spp"
        try:
            yield from self._settle_steps()
        except BaseException:
            before = self._pending
            if before is None:  # the merge before failed: its error, as it is
                raise
            # stopped (Esc, Ctrl-C) while waiting for the merge before: this
            # task is rendered, so it lands too, after that one, without
            # holding up the stop (pending_merge is then this Work)

            def after():
                before.result()
                merge()
            self._start_merge(Work(after, label, mutates=True), self._pending_samples + task.pixels * task.samples)
            raise
        if task.pixels < MERGE_WORK_PIXELS:
            merge()
            return
        # the buffers are whole here: what they will hold once it has landed
        self._start_merge(Work(merge, label, mutates=True), self.samples_rendered + task.pixels * task.samples)

    def _start_merge(self, work, landed: int) -> None:
        self._pending, self._pending_samples = work, landed
        threading.Thread(target=work.run, name="cycles-adaptive-merge", daemon=True).start()

    def _settle_steps(self):
        """:meth:`settle` as steps: a merge still running is yielded as its
        Work first, so a UI waits for it off its main thread."""
        work = self._pending
        if work is None:
            return
        if not work.done:
            yield Progress("merge", self.iteration, self._fraction(), work.label, work=work)
        self.settle()

    def _count_render(self, seconds: float, task) -> None:
        self.cost.add(task.pixels * task.samples, seconds)
        self._last_render_seconds = seconds
        self.timing.render += seconds
        self.max_task_seconds = max(self.max_task_seconds, seconds)

    def _merge(self, task, color, feats) -> None:
        t0 = time.perf_counter()
        merge_render(self.buffers, task, color, feats)
        with self._count_lock:  # the merge added the task's samples to each of its pixels
            if self._count is not None:
                self._count = (self._count[0], self._count[1] + task.pixels * task.samples)
        merge_cryptomatte(self.cryptomatte, self.cryptomatte_header, task, feats.get("cryptomatte"),
                          (self.height, self.width))
        self.tasks_rendered += 1
        self.timing.overhead += time.perf_counter() - t0

    def _render_tasks(self, tasks):
        """Render and merge ``tasks`` in order (through the executor's
        ``render_many`` when it has one); yields each task once its merge has
        started (:meth:`_merge_steps`), and returns once the last has landed.
        Stops before a task once ``max_seconds`` is spent (the tasks merged
        so far are kept)."""
        yield from self._render_and_merge(tasks)
        yield from self._settle_steps()

    def _render_and_merge(self, tasks):
        many = getattr(self.executor, "render_many", None)  # optional member, see module notes
        if many is None:
            for task in tasks:
                if self._time_up():
                    return
                yield from self._merge_steps(task, self._render(task))
                yield task
            return
        results = iter(many(tasks))
        for task in tasks:
            if self._time_up():  # the renders not yet taken are dropped
                close = getattr(results, "close", None)
                if close is not None:
                    close()
                return
            t0 = time.perf_counter()
            rendered = next(results)
            self._count_render(time.perf_counter() - t0, task)
            yield from self._merge_steps(task, lambda r=rendered: r)
            yield task

    def _adapt(self, budget: int):
        """One iteration's adaptation (pure numpy): the reconstruction the
        sampler reads, the sample map and its plan; timed as ``adapt``."""
        t0 = time.perf_counter()
        # a method whose sampler ignores the reconstruction (AWR: Eq. 8 reads
        # the noisy means) says so, and is not reconstructed per iteration;
        # a target check of the same samples already reconstructed them
        if not self.method.SAMPLER_USES_RESULT:
            result = None
        elif self._result is not None and self._result[0] == self.samples_rendered:
            result = self._result[1]
        elif getattr(self.method, "map_result", None) is not None:
            # the method's cheaper reconstruction for maps (core/method.py):
            # not the final one, so neither kept for the end nor its time estimate
            result = self._map_result()
        else:
            t1 = time.perf_counter()
            result = self.method.reconstruct(self.view, self.params)
            if self.timed:  # measured: the final one costs as much, or nothing if no sample follows
                self.reconstruct_estimate = time.perf_counter() - t1
                self._crop_estimate_at = None
                self._result = (self.samples_rendered, result)
        planned = self._plan_iteration(result, budget)
        self.timing.adapt += time.perf_counter() - t0
        return planned

    def _map_result(self):
        """The method's ``map_result``; spread over the executor's workers
        where both can (the executor's optional ``run_jobs`` and
        ``map_parts``, the method's ``fit_band``: LP's bands of rows, the
        same bits as one fit here)."""
        return self.method.map_result(self.view, self.params, **self._spread())

    def _spread(self, final: bool = False) -> dict:
        """Keywords that spread the method's fit over the executor's workers
        (``run``, ``parts``), where both can: the executor's optional
        ``run_jobs`` and ``map_parts``, the method's ``fit_band``.  ``final``
        (the last reconstruction, after every render): the executor may
        compute the jobs here when its workers are gone (``local_fallback``),
        since no render follows that would need them."""
        run = getattr(self.executor, "run_jobs", None)  # optional member, see module notes
        band = getattr(self.method, "fit_band", None)   # optional method member (core/method.py)
        parts = int(getattr(self.executor, "map_parts", 1) or 1)
        if run is None or band is None or parts <= 1:
            return {}
        module, extra = self.method.__name__, ({"local_fallback": True} if final else {})
        return {"run": lambda jobs: run(module, "fit_band", jobs, **extra), "parts": parts}

    def _plan_iteration(self, result, budget: int):
        """Ask the method for ``budget`` samples and plan them into tasks.

        The planner rounds a sparse map up to rectangles when that is cheaper
        than many small renders (the rounded-up samples are rendered and used,
        and counted against the budget).  So the budget handed to the method is
        adjusted (secant steps on a copy of the method's state) until what the
        tasks cover fits this iteration's share (+10 %) and never exceeds what
        remains.  Returns (tasks, covered, counts); the method state of the
        accepted map is kept.
        """
        remaining = self.remaining
        final = budget >= remaining
        limit = remaining if final else min(remaining, int(np.ceil(1.1 * budget)))
        ask = budget
        best = None
        for _ in range(6):
            state = copy.deepcopy(self.method_state)
            counts = self._shaped(self.method.sample_map(self.view, result, max(ask, 0),
                                                         self.params, state))
            plan = self._planned(counts)
            cov = int(plan.covered.sum())
            if cov <= limit and (best is None or cov > best[1].covered.sum()):
                best = (counts, plan, state)
            if cov <= limit and cov >= 0.9 * min(budget, limit):
                break
            if cov <= 0:
                break
            ask = int(ask * min(budget, limit) / cov * (0.97 if cov > limit else 1.0))
            if ask <= 0:
                break
        if best is None:  # even small maps round up past the limit
            state = copy.deepcopy(self.method_state)
            counts = np.asarray(self.method.sample_map(self.view, result, max(limit, 0), self.params,
                                                       state), np.int64)
            # exact plans at block sides 1, 2, 4 .. min_task_size: the one that
            # keeps the most samples within the limit (tasks past it dropped),
            # preferring plans of at most MAX_EXACT_TASKS renders
            best = None
            size = 1
            while True:
                plan = regions.plan(counts, frame=self.options.frame, min_size=size, task_cost=0.0)
                kept = _within(plan, limit)
                got = int(kept[1].sum())
                key = (0 < len(kept[0]) <= MAX_EXACT_TASKS and got > 0, got)
                if best is None or key > best[0]:
                    best = (key, kept)
                if size >= self.options.min_task_size:
                    break
                size = min(2 * size, self.options.min_task_size)
            tasks, covered = best[1]
            self.method_state = state
            self.overshoot += max(0, int(covered.sum()) - int(counts.sum()))
            return tasks, covered, counts
        counts, plan, state = best
        self.method_state = state
        tasks, covered = _within(plan, limit)
        self.overshoot += max(0, int(covered.sum()) - int(counts.sum()))
        return tasks, covered, counts

    # ----------------------------------------------------------------- result
    def method_reconstruction(self):
        """The method's own reconstruction of the samples so far, before the
        guard: of :attr:`view` (the passes that carry information), spread
        over the executor's workers; the target check's result when it saw
        these very samples.  A frame-range reconstructor builds on this."""
        if self._result is not None and self._result[0] == self.samples_rendered:
            return self._result[1]
        return self.method.reconstruct(self.view, self.params, **self._spread(final=True))

    def reconstruct(self, reconstructor=None):
        """Final reconstruction (the method's, or ``reconstructor(run)``),
        through the consistency guard of ``Options.guard_z``."""
        self.settle()
        t0 = time.perf_counter()
        result = self.method_reconstruction() if reconstructor is None else reconstructor(self)
        guard = self.options.guard_z
        if self.selection is not None and "guard_z" in self.selection:  # the selecting method's choice
            guard = float(self.selection["guard_z"])
        result = consistency_guard(result, self.buffers, guard)
        self.timing.reconstruct += time.perf_counter() - t0
        return result

    # ------------------------------------------------------------- checkpoint
    def _checkpoint(self):
        """Steps that write the checkpoint as a Work (packing and writing it
        takes seconds at 1920x1080: off the UI's main thread)."""
        if not self.checkpoint_path or self.buffers is None:
            return
        yield from self._settle_steps()
        work = Work(self._save_checkpoint, f"iteration {self.iteration}: writing the checkpoint")
        yield Progress("saving", self.iteration, self._fraction(), work.label, work=work)
        work.result()

    def _save_checkpoint(self) -> None:
        if not self.checkpoint_path or self.buffers is None:
            return
        meta = {"options": _options_key(self.options), "method": self.method.NAME,
                "iteration": self.iteration, "tasks_rendered": self.tasks_rendered,
                "overshoot": self.overshoot, "timing": asdict(self.timing), "history": self.history,
                "exponent": self.buffers.exponent, "selection": self.selection,
                "dropped": list(self.dropped), "cryptomatte_header": self.cryptomatte_header}
        arrays = {"next_index": self.next_index, "reused": self.reused}
        if self.buffers.gsum is not None:
            arrays["gsum"] = self.buffers.gsum
        for base, acc in self.cryptomatte.items():
            arrays.update({f"crypto__{base}__{k}": v for k, v in acc.state().items()})
        storage.save_checkpoint(self.checkpoint_path, self.buffers, arrays, meta, self.method_state)

    def load_checkpoint(self, path: str) -> None:
        """Continue from a checkpoint written by a run with the same options
        (``core.storage``: plain arrays and JSON, nothing unpickled)."""
        b, arrays, meta, state = storage.load_checkpoint(path)
        sel = meta.get("selection")
        if sel and selects(self.method):  # the choice made before the checkpoint
            try:
                self._adopt(self.method.resolve(sel["chosen"]), sel, sel.get("params") or {})
            except (KeyError, TypeError, ValueError) as exc:
                raise ValueError(f"{path}: checkpoint's choice is unreadable ({exc})") from None
        if meta.get("options") != _options_key(self.options) or meta.get("method") != self.method.NAME:
            raise ValueError(f"{path}: checkpoint was made with other settings "
                             f"({meta.get('method')}, {meta.get('options')}); use the same options to resume")
        if b.n.shape != (self.height, self.width):
            raise ValueError(f"{path}: checkpoint is {b.n.shape}, the render is "
                             f"{(self.height, self.width)}")
        b.exponent = float(meta.get("exponent", 1.0))
        gsum = arrays.get("gsum")
        b.gsum = None if gsum is None or np.shape(gsum) != b.n.shape else np.asarray(gsum, np.float64)
        self.buffers = b
        self._count = None
        self.dropped = tuple(p for p in meta.get("dropped", []) if p in b.features)
        self._stop_rendering()
        self.next_index = arrays["next_index"]
        self.reused = arrays.get("reused", np.zeros((self.height, self.width)))
        self.cryptomatte_header = dict(meta.get("cryptomatte_header") or {})
        self.cryptomatte = {}
        for base in self.cryptomatte_header:
            try:
                acc = cryptomatte.CryptoAccumulator.from_state(
                    {k: arrays[f"crypto__{base}__{k}"] for k in ("ids", "wcov", "weight")})
            except (KeyError, ValueError) as exc:
                raise ValueError(f"{path}: checkpoint's Cryptomatte {base!r} is unreadable ({exc})") from None
            if acc.weight.shape != (self.height, self.width):
                raise ValueError(f"{path}: checkpoint's Cryptomatte {base!r} is {acc.weight.shape}")
            self.cryptomatte[base] = acc
        self.iteration = int(meta["iteration"])
        self.tasks_rendered = int(meta["tasks_rendered"])
        self.overshoot = int(meta["overshoot"])
        self.history = list(meta.get("history", []))
        self.method_state = state


def selects(method) -> bool:
    """A selecting method (``core.auto``): it chooses the method to run from
    the initial pass (``cv_regions``, ``select``, ``resolve``) instead of
    sampling itself."""
    return all(hasattr(method, m) for m in ("cv_regions", "select", "resolve"))


def held_count(options: Options, method, prior=None) -> int | None:
    """The one sample count every pixel of a run ends with, known before its
    first render: a method that samples uniformly (``ADAPTIVE`` off) at an
    integral ``spp``, without a time limit, a target error or samples carried
    from an earlier frame (``prior``), with ``Options.scene_pattern`` on; its
    initial pass renders the whole budget as subsets of ``[0, spp)``.  None
    otherwise.  An executor may then render with a count-tuned pattern
    (``CyclesExecutor.hold_samples_at``).

    A selecting method (``auto``) holds it too: its initial pass is the
    subsets ``[0, initial)`` of the held count, and a uniform choice renders
    the rest as subsets up to ``spp``, so the image is the scene pattern's
    ``spp`` render, as for that candidate run alone.  An adaptive choice ends
    the hold (:meth:`AdaptiveRun._adopt`, the executor's ``release_hold``)
    before its first render: its samples after the initial pass come from a
    count-independent pattern (each part of the mean is unbiased, so the
    merge is too)."""
    spp = float(options.spp)
    if not options.scene_pattern or (method.ADAPTIVE and not selects(method)) or prior is not None:
        return None
    if selects(method) and (options.params or {}).get("sampling") == "adaptive":
        return None  # told to choose among adaptive candidates only: no uniform choice to hold for
    if options.max_seconds > 0 or options.target_error > 0 or spp < 1 or spp != np.floor(spp):
        return None
    return int(spp)


def hold_samples(executor, options: Options, method, prior=None) -> int | None:
    """Tell ``executor`` the run's one final count (:func:`held_count`)
    through its optional ``hold_samples_at``, before it is entered; the
    count, or None where there is none (or the executor cannot hold it; for
    a selecting method, also where it cannot release it again)."""
    count = held_count(options, method, prior)
    hold = getattr(executor, "hold_samples_at", None)  # optional member, see module notes
    if count is None or hold is None:
        return None
    if selects(method) and getattr(executor, "release_hold", None) is None:
        return None  # an adaptive choice could not leave the count-tuned pattern
    hold(count)
    return count


def _within(plan, limit: int):
    """(tasks, covered) of a plan with its last tasks dropped until it covers
    at most ``limit`` samples."""
    tasks, covered = list(plan.tasks), plan.covered.copy()
    while tasks and int(covered.sum()) > limit:
        t = tasks.pop()
        covered[t.y0:t.y1, t.x0:t.x1] -= t.samples
    return tasks, covered


#: target-error schedule (next_target_spp): each round aims at this share of
#: the target, so a check lands below it despite the estimate's noise ...
TARGET_AIM = 0.9
#: ... grows the samples by at most this factor (a bad fit cannot overshoot
#: by more than one doubling, the old schedule's step) and at least by this
#: one (a check just above the target is not followed by a string of tiny steps)
TARGET_MAX_GROWTH = 2.0
TARGET_MIN_GROWTH = 1.1
#: the fitted rate is clamped to this range; the first step (one check, no
#: fit) assumes 1, the rate of an unbiased mean of independent samples
TARGET_RATE_RANGE = (0.25, 2.0)
TARGET_PRIOR_RATE = 1.0
#: the rate is fitted between the latest check and the latest one at least
#: this factor fewer spp before it (the earliest where none is)
TARGET_FIT_SPAN = 1.5


def convergence_rate(estimates) -> float | None:
    """Rate ``q`` of ``est ~ C spp^-q`` through two checks ``(spp, est)``: the
    latest and the latest earlier one with at most ``1 / TARGET_FIT_SPAN`` of
    its spp (else the earliest), ``q = log(e0 / e1) / log(n1 / n0)``, clamped
    to ``TARGET_RATE_RANGE`` (an estimate that grew gives the smallest rate,
    i.e. the largest step).  None without two usable checks (positive, finite,
    increasing spp)."""
    pts = [(float(n), float(e)) for n, e in estimates]
    if len(pts) < 2:
        return None
    n1, e1 = pts[-1]
    earlier = [p for p in pts[:-1] if p[0] * TARGET_FIT_SPAN <= n1]
    n0, e0 = earlier[-1] if earlier else pts[0]
    if not (np.isfinite([n0, n1, e0, e1]).all() and n1 > n0 > 0 and e0 > 0 and e1 > 0):
        return None
    q = np.log(e0 / e1) / np.log(n1 / n0)
    return float(np.clip(q, *TARGET_RATE_RANGE))


def next_target_spp(estimates, target: float) -> float:
    """The spp of the next target check from the checks ``(spp, est)`` so far
    (the last one above ``target``): with ``est = C n^-q`` through the last
    check ``(n, e)`` (``q``: :func:`convergence_rate`, ``TARGET_PRIOR_RATE``
    with one check) the spp where it reaches ``TARGET_AIM * target``,

        n' = n (e / (TARGET_AIM target))^(1/q),

    clamped to ``[TARGET_MIN_GROWTH n, TARGET_MAX_GROWTH n]``.  The last round
    thus lands near the target instead of at the next power of two, and a
    rate measured below 1 (a denoiser's, a stratified sequence's above it)
    steps accordingly."""
    n, e = (float(v) for v in estimates[-1])
    q = convergence_rate(estimates) or TARGET_PRIOR_RATE
    aim = TARGET_AIM * float(target)
    if not (np.isfinite(e) and e > 0 and aim > 0):
        return TARGET_MAX_GROWTH * n
    with np.errstate(over="ignore", divide="ignore"):
        growth = (np.float64(e) / np.float64(aim)) ** (1.0 / q)  # inf beyond float range: the clamp
    return float(n * np.clip(growth, TARGET_MIN_GROWTH, TARGET_MAX_GROWTH))


def subset_tasks(width: int, height: int, spp: int, subsets: int, frame: int = 0,
                 offset: int = 0) -> list:
    """Full-frame tasks rendering ``spp`` samples as ``subsets`` disjoint,
    consecutive sample subsets starting at ``offset`` (sizes differ by at most
    one): merged, they are one ``spp`` render with a variance estimate of
    ``subsets - 1`` degrees of freedom (``core/buffers.py``)."""
    k = max(1, min(int(subsets), int(spp)))
    base, extra = divmod(int(spp), k)
    tasks = []
    for s in range(k):
        count = base + (1 if s < extra else 0)
        tasks.append(regions.RegionTask(0, 0, int(width), int(height), count, frame=frame, offset=offset))
        offset += count
    return tasks


def merge_render(buffers: Buffers, task, color, features) -> None:
    """Merge one rendered task (an executor's ``(color, features)``) into
    ``buffers`` as one sample group over the task's rectangle.  Alpha
    (``color``'s 4th channel, 1 without one) rides along as the ``alpha``
    pass; passes ``buffers`` does not keep are dropped.  A pass the render
    does not carry keeps its accumulated mean where every pixel of the task
    already has samples: a pass no longer rendered (constant in this frame),
    or one Cycles writes only in the render holding sample 0 (Position,
    IndexOB: ``addon/executor.py``); elsewhere it is an error (KeyError)."""
    color = np.asarray(color, np.float64)
    feats = dict(features)
    sl = (slice(task.y0, task.y1), slice(task.x0, task.x1))
    missing = [k for k in buffers.features if k not in feats and k != "alpha"]
    if missing and np.all(buffers.n[sl] > 0):
        for name in missing:
            feats[name] = buffers.features[name].mean[sl]
    if "alpha" not in feats:
        feats["alpha"] = color[:, :, 3:4] if color.shape[2] >= 4 else np.ones(color.shape[:2] + (1,))
    buffers.merge_group(color[:, :, :3], task.samples,
                        {k: v for k, v in feats.items() if k in buffers.features},
                        region=(task.x0, task.y0, task.x1, task.y1))


#: ranks an accumulator keeps per rendered rank (the output keeps the render's
#: own count): ids that no single render ranked first still find a slot
CRYPTOMATTE_SLACK = 2


def merge_cryptomatte(accumulators: dict, headers: dict, task, ranks, shape) -> None:
    """Merge one task's Cryptomatte ranks (the executor's
    ``features["cryptomatte"]``: base -> (ids, coverage, header); None or
    empty: nothing) into ``accumulators`` (base -> CryptoAccumulator, made
    at the first render, ``shape`` (H, W), with ``CRYPTOMATTE_SLACK`` x its
    levels: the output's levels are ``capacity // CRYPTOMATTE_SLACK``) over the
    task's rectangle, weighted by the task's samples (coverage is the
    fraction of a render's samples); ``headers`` keeps each base's header
    attributes, the manifests' entries united."""
    if not ranks:
        return
    for base, (ids, cov, header) in ranks.items():
        acc = accumulators.get(base)
        if acc is None:
            acc = accumulators[base] = cryptomatte.CryptoAccumulator(
                shape[0], shape[1], CRYPTOMATTE_SLACK * ids.shape[2])
        acc.merge(ids, cov, task.samples, region=(task.x0, task.y0, task.x1, task.y1))
        old = headers.get(base, {})
        new = dict(old, **header)
        try:
            manifest = dict(json.loads(old.get("manifest") or "{}"), **json.loads(header.get("manifest") or "{}"))
            new["manifest"] = json.dumps(manifest, separators=(",", ":"))
        except (TypeError, ValueError):
            pass
        headers[base] = new


def render_subsets(executor, buffers: Buffers, spp: int, subsets: int, frame: int = 0) -> Buffers:
    """Render ``spp`` samples of the executor's whole domain as sample subsets
    (:func:`subset_tasks`) and merge them into ``buffers``; returns it."""
    h, w = executor.size
    for task in subset_tasks(w, h, spp, subsets, frame):
        merge_render(buffers, task, *executor.render(task))
    return buffers


def _stack_rows(parts: list) -> np.ndarray:
    """Bands of rows (top to bottom) as one array; one band as it is."""
    return np.asarray(parts[0]) if len(parts) == 1 else np.concatenate([np.asarray(p) for p in parts], axis=0)


def _options_key(o: Options) -> dict:
    d = asdict(o)
    d.pop("max_seconds", None)
    d.pop("render_seconds", None)  # how renders are cut, not what they hold
    if not d.get("target_error"):  # checkpoints from before the option resume
        d.pop("target_error", None)
    if d.get("scene_pattern", True):  # likewise (an adaptive run renders Tabulated Sobol either way)
        d.pop("scene_pattern", None)
    d["features"] = list(d["features"])
    return json.loads(json.dumps(d, sort_keys=True, default=str))
