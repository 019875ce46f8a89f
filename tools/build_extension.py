"""Build the extension: one zip per platform, each with the OpenImageIO wheel it needs (and the
pure-Python wheels every platform shares).

    python tools/build_extension.py                        # -> build/extension/*.zip
    python tools/build_extension.py --output-dir DIR
    python tools/build_extension.py --blender /path/to/blender   # use an installed Blender's tool
    python tools/build_extension.py --fetch-only           # only fill wheels/

Blender's extension docs ("Python Wheels") ask for unmodified wheels from PyPI listed in
``blender_manifest.toml`` (``wheels = [...]``) and one build per platform
(``build --split-platforms``, which needs ``platforms``).  The manifest is the one list: each wheel's
file name spells the distribution, pinned version, Python tag and platform tag, and this script asks
pip for exactly that file (``pip download --only-binary=:all: --no-deps --platform ...
--python-version ...``) into ``wheels/`` (git-ignored; a wheel already there is not fetched again).
It then runs the extension tool of the ``bpy`` module installed in this Python
(``bpy/<version>/scripts/addons_core/bl_pkg/cli/blender_ext.py``), or ``blender -c extension`` with
``--blender``.

Exit codes: 0 built, 2 bad input (one line on stderr), 3 the package index could not be reached,
1 any other failure.
"""
from __future__ import annotations

import argparse
import glob
import importlib.util
import os
import shutil
import subprocess
import sys
import tempfile
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
EXIT_BAD_INPUT, EXIT_OFFLINE = 2, 3
# a pure-Python wheel (py3-none-any) is asked for as Blender 4.2-5.0's Python would install it
PURE_PYTHON_VERSION = "3.11"

# What pip prints (urllib3 / requests) when the index cannot be reached at all, as opposed to a
# reachable index without the requested file.
OFFLINE_MARKERS = ("NewConnectionError", "ConnectTimeoutError", "Max retries exceeded",
                   "Network is unreachable", "Temporary failure in name resolution",
                   "Name or service not known", "ProxyError", "Connection refused",
                   "No route to host", "ReadTimeoutError")


class BuildError(Exception):
    """A failure with a one-line message; ``code`` is the exit code."""

    def __init__(self, message: str, code: int = 1):
        super().__init__(message)
        self.code = code


def read_manifest(root: str = ROOT) -> dict:
    """The parsed ``blender_manifest.toml`` of ``root``."""
    path = os.path.join(root, "blender_manifest.toml")
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise BuildError(f"{path}: {exc}", EXIT_BAD_INPUT) from exc


def wheel_request(rel_path: str) -> dict:
    """What to ask pip for to get the wheel file ``rel_path`` names.

    The wheel file name is ``{dist}-{version}(-{build})?-{python}-{abi}-{platform}.whl``
    (PEP 427); a compressed tag set (``manylinux_2_27_x86_64.manylinux_2_28_x86_64``) is asked
    for by its last tag, which pip widens to the older ones.
    """
    name = os.path.basename(rel_path)
    parts = name[:-len(".whl")].split("-") if name.endswith(".whl") else []
    if not 5 <= len(parts) <= 6:
        raise BuildError(f"blender_manifest.toml: {rel_path!r} is not a wheel file name", EXIT_BAD_INPUT)
    dist, version, py_tag, abi, platform = parts[0], parts[1], parts[-3], parts[-2], parts[-1]
    if (py_tag, abi, platform) == ("py3", "none", "any"):          # pure Python: one for all
        return {"file": name, "requirement": f"{dist}=={version}", "pure": True,
                "python_version": PURE_PYTHON_VERSION}
    if not (py_tag.startswith("cp") and py_tag[2:].isdigit() and len(py_tag) >= 4):
        raise BuildError(f"blender_manifest.toml: {name}: expected a CPython tag such as cp311",
                         EXIT_BAD_INPUT)
    return {"file": name, "requirement": f"{dist}=={version}", "abi": abi,
            "python_version": f"{py_tag[2]}.{py_tag[3:]}", "platform": platform.split(".")[-1]}


def manifest_wheels(manifest: dict) -> list[str]:
    """The manifest's wheel paths, checked to lie in ``./wheels/``."""
    wheels = manifest.get("wheels") or []
    for w in wheels:
        if not w.startswith("./wheels/") or "/" in w[len("./wheels/"):]:
            raise BuildError(f"blender_manifest.toml: {w!r}: wheels must lie directly in ./wheels/",
                             EXIT_BAD_INPUT)
    return wheels


def missing_wheels(root: str = ROOT, manifest: dict | None = None) -> list[str]:
    """File names of the manifest's wheels not yet in ``root/wheels``."""
    manifest = read_manifest(root) if manifest is None else manifest
    return [os.path.basename(w) for w in manifest_wheels(manifest)
            if not os.path.isfile(os.path.join(root, "wheels", os.path.basename(w)))]


def _pip_download(req: dict, dest: str, python: str) -> None:
    """Download exactly the wheel ``req`` describes into ``dest`` (a fresh folder)."""
    target = (["--python-version", req["python_version"]] if req.get("pure") else
              ["--implementation", "cp", "--abi", req["abi"], "--platform", req["platform"],
               "--python-version", req["python_version"]])
    cmd = [python, "-m", "pip", "download", "--disable-pip-version-check", "--no-input",
           "--only-binary=:all:", "--no-deps", *target,
           "--retries", "2", "--timeout", "20", "--dest", dest, req["requirement"]]
    run = subprocess.run(cmd, capture_output=True, text=True)
    if run.returncode != 0:
        out = run.stdout + run.stderr
        errors = [ln.strip() for ln in out.splitlines() if ln.strip().startswith("ERROR")]
        last = errors[-1] if errors else (out.strip().splitlines() or ["pip failed"])[-1]
        if any(m in out for m in OFFLINE_MARKERS):
            raise BuildError(f"cannot reach the package index to fetch {req['file']} ({last})",
                             EXIT_OFFLINE)
        raise BuildError(f"pip could not fetch {req['file']}: {last}")
    got = sorted(os.listdir(dest))
    if got != [req["file"]]:
        raise BuildError(f"asked pip for {req['file']}, got {got}: fix the name in blender_manifest.toml")


def fetch_wheels(root: str = ROOT, python: str = sys.executable, log=print) -> list[str]:
    """Fetch every wheel of the manifest missing from ``root/wheels``; return all their paths.

    Each download lands in a temporary folder beside the cache and is moved in whole, so a killed
    run or two runs at once never leave a partial wheel under its final name.
    """
    manifest = read_manifest(root)
    wheel_dir = os.path.join(root, "wheels")
    os.makedirs(wheel_dir, exist_ok=True)
    for rel in manifest_wheels(manifest):
        req = wheel_request(rel)
        final = os.path.join(wheel_dir, req["file"])
        if os.path.isfile(final):
            continue
        log(f"fetching {req['file']}")
        with tempfile.TemporaryDirectory(dir=wheel_dir, prefix=".fetch-") as tmp:
            _pip_download(req, tmp, python)
            os.replace(os.path.join(tmp, req["file"]), final)
    return [os.path.join(wheel_dir, os.path.basename(w)) for w in manifest_wheels(manifest)]


def extension_tool(python: str = sys.executable) -> str:
    """Path of ``blender_ext.py`` inside the ``bpy`` module of ``python`` (found without importing bpy)."""
    probe = ("import importlib.util, sys; s = importlib.util.find_spec('bpy'); "
             "sys.stdout.write(s.origin if s and s.origin else '')")
    if os.path.realpath(python) == os.path.realpath(sys.executable):
        spec = importlib.util.find_spec("bpy")
        origin = spec.origin if spec and spec.origin else ""
    else:
        origin = subprocess.run([python, "-c", probe], capture_output=True, text=True).stdout
    found = sorted(glob.glob(os.path.join(os.path.dirname(origin), "*", "scripts", "addons_core",
                                          "bl_pkg", "cli", "blender_ext.py"))) if origin else []
    if not found:
        raise BuildError(f"no bpy module with blender_ext.py in {python}: install bpy "
                         f"(bash setup.sh) or pass --blender /path/to/blender", EXIT_BAD_INPUT)
    return found[-1]


def expected_zips(manifest: dict, out_dir: str) -> dict[str, str]:
    """Platform -> zip path that ``build --split-platforms`` writes for it."""
    return {p: os.path.join(out_dir, f"{manifest['id']}-{manifest['version']}-{p.replace('-', '_')}.zip")
            for p in manifest["platforms"]}


def build(root: str = ROOT, out_dir: str | None = None, blender: str | None = None,
          python: str = sys.executable, log=print) -> dict[str, str]:
    """Fetch the wheels and build one zip per platform; return platform -> zip path."""
    manifest = read_manifest(root)
    if not manifest.get("platforms"):
        raise BuildError("blender_manifest.toml declares no platforms", EXIT_BAD_INPUT)
    out_dir = os.path.abspath(out_dir or os.path.join(root, "build", "extension"))
    os.makedirs(out_dir, exist_ok=True)
    args = ["build", "--source-dir", root, "--output-dir", out_dir, "--split-platforms"]
    if blender:
        if shutil.which(blender) is None:
            raise BuildError(f"{blender}: no such program", EXIT_BAD_INPUT)
        cmd = [blender, "--factory-startup", "--command", "extension", *args]
    else:
        cmd = [python, extension_tool(python), *args]
    fetch_wheels(root, python, log)
    run = subprocess.run(cmd, capture_output=True, text=True)
    zips = expected_zips(manifest, out_dir)
    if run.returncode != 0 or not all(os.path.isfile(z) for z in zips.values()):
        lines = (run.stdout + run.stderr).strip().splitlines() or ["no output"]
        raise BuildError(f"extension build failed (exit {run.returncode}): {lines[-1]}")
    for platform, path in zips.items():
        log(f"built {_shown(path)} ({platform}, {os.path.getsize(path) / 1e6:.1f} MB)")
    return zips


def _shown(path: str) -> str:
    """``path`` relative to the working folder when inside it, else absolute."""
    rel = os.path.relpath(path)
    return path if rel.startswith("..") else rel


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    ap.add_argument("--output-dir", default=os.path.join(ROOT, "build", "extension"),
                    help="folder for the zips")
    ap.add_argument("--blender", default=None,
                    help="a Blender executable whose `-c extension build` to use instead of bpy's tool")
    ap.add_argument("--fetch-only", action="store_true", help="only fetch the wheels into wheels/")
    args = ap.parse_args(argv)
    try:
        if args.fetch_only:
            for path in fetch_wheels():
                print(_shown(path))
        else:
            build(out_dir=args.output_dir, blender=args.blender)
    except BuildError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.code
    return 0


if __name__ == "__main__":
    sys.exit(main())
