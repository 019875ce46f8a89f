"""Launcher for ./cycles-adaptive: imports the repository as the package
``cycles_adaptive`` (the same package layout Blender uses for the extension)
and runs the command line with the repository's developer commands
(``bench``, ``references``: :data:`bench.COMMANDS`).  Not part of the built
extension."""
import importlib.util
import os
import sys

ROOT = os.path.dirname(os.path.abspath(__file__))


def load_package(name: str = "cycles_adaptive", root: str = ROOT):
    """The repository at ``root`` (default this one) imported as package ``name``
    (another tree under another name lets a tool compare two versions)."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, os.path.join(root, "__init__.py"),
                                                  submodule_search_locations=[root])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


def leave(code: int) -> None:
    """Exit with ``code`` once the command is done.  With the bpy module
    loaded, after the exit hooks Python would run (the stepper's wait for
    running writes), the process leaves without
    running bpy's C++ static destructors: bpy 4.x can hang in them forever
    (its sound-device thread's condition variable; seen with gdb on a process
    whose work was done), which would stall a farm job after its frame was
    written."""
    sys.stdout.flush()
    sys.stderr.flush()
    if "bpy" not in sys.modules:
        sys.exit(code)
    import atexit
    atexit._run_exitfuncs()  # the exit hooks a normal exit runs (the stepper waits for its writes there)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


if __name__ == "__main__":
    load_package()
    from cycles_adaptive.bench import COMMANDS
    from cycles_adaptive.operators import cli, farm, farm_job
    leave(cli.main(sys.argv[1:], extra_commands=tuple(COMMANDS) + (farm_job, farm.WORKER)))
