"""Test set-up shared by all tests: bpy runs as a module with its user resources isolated."""
import atexit
import os
import shutil
import tempfile

# Before anything imports bpy: never touch the developer's own Blender configuration.
if "BLENDER_USER_RESOURCES" not in os.environ:
    os.environ["BLENDER_USER_RESOURCES"] = tempfile.mkdtemp(prefix="sglf-blender-user-")
    atexit.register(shutil.rmtree, os.environ["BLENDER_USER_RESOURCES"], ignore_errors=True)

# The repository is the package sg_lightfield (its modules import each other relatively; sg_launch.py).
import sg_launch  # noqa: E402  (after the user-resources set-up above, which must precede bpy)

sg_launch.load_package()
