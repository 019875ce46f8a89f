import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

# Import the repository as the package ``cycles_adaptive`` (as Blender does for
# the extension), so relative imports between addon/, operators/ and core/ work.
sys.path.insert(0, os.path.join(ROOT, "tests"))
from launch import load_package  # noqa: E402

load_package()

# auto's measured reconstruction costs (core/auto.py) go to one folder per test
# session, shared with the CLI subprocesses, never to the user's cache
if "CYCLES_ADAPTIVE_CACHE" not in os.environ:
    import tempfile

    os.environ["CYCLES_ADAPTIVE_CACHE"] = tempfile.mkdtemp(prefix="cycles-adaptive-test-cache-")


# bpy 4.x can hang forever after the session, in its C++ static destructors: its
# ~GlobalState destroys a condition variable its own sound-device thread
# (delayed_close_thread_run) still waits on (gdb on a hung test process, 2026-12-02:
# every test had passed; main thread in __pthread_cond_destroy under exit()).  The
# results are printed and written by then, so the test process leaves at once with
# pytest's exit status instead of running the destructors.
_EXIT_STATUS = []


def pytest_sessionfinish(session, exitstatus):
    _EXIT_STATUS.append(int(exitstatus))


def pytest_unconfigure(config):
    if _EXIT_STATUS and "bpy" in sys.modules:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_EXIT_STATUS[-1])
