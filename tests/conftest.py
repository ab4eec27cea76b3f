"""Test set-up shared by all tests: bpy runs as a module with its user resources isolated."""
import atexit
import os
import shutil
import tempfile

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
