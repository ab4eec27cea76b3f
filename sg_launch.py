"""How the repository's code is started outside Blender's extension system: as the package ``sg_lightfield``.

Inside the package every module imports its siblings relatively (``from ..bake_directory.bake_plan import ...``): that is
the one import mechanism, and it is what Blender does for the installed extension (``bl_ext.<repo>.sg_lightfield``).
Entry points run as files (``python headless/bake.py``, ``blender -b -P headless/bake.py``), with ``python -m
headless.bench`` or by the add-on's training worker start here; so do the tests (their conftest).
"""
from __future__ import annotations

import importlib.util
import runpy
import sys
from pathlib import Path

PACKAGE = "sg_lightfield"
ROOT = Path(__file__).resolve().parent


def load_package():
    """The repository as the package `sg_lightfield` (loaded once from its folder, whatever the folder is called)."""
    module = sys.modules.get(PACKAGE)
    if module is None:
        spec = importlib.util.spec_from_file_location(PACKAGE, ROOT / "__init__.py",
                                                      submodule_search_locations=[str(ROOT)])
        module = importlib.util.module_from_spec(spec)
        sys.modules[PACKAGE] = module
        spec.loader.exec_module(module)
    return module


def run_in_package(path) -> None:
    """Run the module file `path` of the repository as `__main__` inside the package, then exit."""
    load_package()
    parts = Path(path).resolve().relative_to(ROOT).with_suffix("").parts
    runpy.run_module(".".join((PACKAGE, *parts)), run_name="__main__", alter_sys=True)
    raise SystemExit(0)
