"""Launcher for ./cycles-adaptive: imports the repository as the package
``cycles_adaptive`` (the same package layout Blender uses for the extension)
and runs the command line with the repository's developer commands
(``bench``, ``references``: :data:`bench.COMMANDS`).  Not part of the built
extension."""
import importlib.util
import os
import sys

ROOT = os.path.dirname(os.path.abspath(__file__))


def load_package(name: str = "cycles_adaptive"):
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, os.path.join(ROOT, "__init__.py"),
                                                  submodule_search_locations=[ROOT])
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod


if __name__ == "__main__":
    load_package()
    from cycles_adaptive.bench import COMMANDS
    from cycles_adaptive.operators import cli, farm, farm_job
    sys.exit(cli.main(sys.argv[1:], extra_commands=tuple(COMMANDS) + (farm_job, farm.WORKER)))
