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
