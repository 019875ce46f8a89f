"""tools/build_extension.py without building: what pip is asked for each wheel the manifest names
(platform wheels and pure-Python ones), and that every manifest wheel is pinned in the requirements."""
import importlib.util
import os
import subprocess

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
_spec = importlib.util.spec_from_file_location("build_extension",
                                               os.path.join(ROOT, "tools", "build_extension.py"))
build_extension = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(build_extension)


def test_a_platform_wheel_is_asked_for_by_its_tags():
    req = build_extension.wheel_request(
        "./wheels/openimageio-3.0.21.0-cp311-cp311-manylinux_2_27_x86_64.manylinux_2_28_x86_64.whl")
    assert req["requirement"] == "openimageio==3.0.21.0"
    assert (req["abi"], req["python_version"], req["platform"]) == ("cp311", "3.11", "manylinux_2_28_x86_64")
    assert not req.get("pure")


def test_a_pure_wheel_is_asked_for_once_for_every_platform():
    req = build_extension.wheel_request("./wheels/threadpoolctl-3.6.0-py3-none-any.whl")
    assert req == {"file": "threadpoolctl-3.6.0-py3-none-any.whl", "requirement": "threadpoolctl==3.6.0",
                   "pure": True, "python_version": build_extension.PURE_PYTHON_VERSION}


@pytest.mark.parametrize("name", ["./wheels/notawheel.zip", "./wheels/a-1.0.whl",
                                  "./wheels/a-1.0-py2-none-any.whl", "./wheels/a-1.0-py3-abi3-win_amd64.whl"])
def test_other_names_are_bad_input(name):
    with pytest.raises(build_extension.BuildError) as exc:
        build_extension.wheel_request(name)
    assert exc.value.code == build_extension.EXIT_BAD_INPUT


def test_pip_is_asked_without_platform_tags_for_a_pure_wheel(monkeypatch, tmp_path):
    seen = []

    def fake_run(cmd, capture_output, text):
        seen.append(cmd)
        dest = cmd[cmd.index("--dest") + 1]
        open(os.path.join(dest, "threadpoolctl-3.6.0-py3-none-any.whl"), "wb").close()
        return subprocess.CompletedProcess(cmd, 0, "", "")

    monkeypatch.setattr(build_extension.subprocess, "run", fake_run)
    req = build_extension.wheel_request("./wheels/threadpoolctl-3.6.0-py3-none-any.whl")
    build_extension._pip_download(req, str(tmp_path), "python")
    cmd = seen[0]
    assert "--platform" not in cmd and "--abi" not in cmd
    assert cmd[cmd.index("--python-version") + 1] == "3.11"
    assert "--only-binary=:all:" in cmd and "--no-deps" in cmd and cmd[-1] == "threadpoolctl==3.6.0"


def test_every_bundled_wheel_is_pinned_in_every_requirements_file():
    manifest = build_extension.read_manifest(ROOT)
    pins = {}
    for name in ("requirements.txt", "requirements-4.2.txt", "requirements-5.0.txt"):
        with open(os.path.join(ROOT, name)) as fh:
            pins[name] = {ln.split("==")[0].strip().lower(): ln.split("==")[1].strip()
                          for ln in fh if "==" in ln and not ln.startswith("#")}
    for w in build_extension.manifest_wheels(manifest):
        req = build_extension.wheel_request(w)
        dist, version = req["requirement"].split("==")
        for name, pinned in pins.items():
            assert pinned.get(dist.lower()) == version, (name, w)
