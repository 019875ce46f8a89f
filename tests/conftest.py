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
