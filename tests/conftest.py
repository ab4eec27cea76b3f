"""Test set-up shared by all tests: bpy runs as a module with its user resources isolated."""
import atexit
import os
import shutil
import sys
import tempfile

import pytest

# Before anything imports bpy: never touch the developer's own Blender configuration. Each pytest-xdist worker
# gets a directory of its own (tests install extensions into it), not the one its parent process made.
_OWNER = "SGLF_TEST_USER_RESOURCES_PID"
if "BLENDER_USER_RESOURCES" not in os.environ or os.environ.get(_OWNER, str(os.getpid())) != str(os.getpid()):
    worker = os.environ.get("PYTEST_XDIST_WORKER", "main")
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix=f"sglf-blender-user-{worker}-")
    os.environ[_OWNER] = str(os.getpid())
    atexit.register(shutil.rmtree, os.environ["BLENDER_USER_RESOURCES"], ignore_errors=True)

# The repository is the package sg_lightfield (its modules import each other relatively; sg_launch.py).
import sg_launch  # noqa: E402  (after the user-resources set-up above, which must precede bpy)

sg_launch.load_package()


# The files that take longest on a 2-core machine (pytest --durations), handed to the pytest-xdist workers first so
# that no long file starts last (make test: --dist loadfile --no-loadscope-reorder); the rest keep their order.
LONGEST_FIRST = ("test_apply.py", "test_materials.py", "test_blender_versions.py", "test_geometry.py", "test_farm.py",
                 "test_operator.py")


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))


@pytest.fixture(autouse=True)
def remove_bakes_a_test_leaves():
    """A test that fails before its own Remove SG Bake would leave its scene baked, and the bake's shared node groups
    and images stay while any scene is baked: the next tests in the process would find them. After each test, every
    scene the test baked (one not baked before it) has its bake removed; a module fixture's bake is its own to
    remove."""
    baked_before = _baked_scenes()
    yield
    left = _baked_scenes() - baked_before
    if left:
        import bpy

        from sg_lightfield.blender_addon.apply import remove_bake

        for name in left:
            scene = bpy.data.scenes.get(name)
            if scene is not None:
                remove_bake(scene)


def _baked_scenes() -> set:
    bpy = sys.modules.get("bpy")  # a test that never imported bpy baked nothing
    if bpy is None:
        return set()
    from sg_lightfield.blender_addon.apply import BAKE_RECORD_KEY

    return {scene.name for scene in bpy.data.scenes if BAKE_RECORD_KEY in scene}
