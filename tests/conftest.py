"""Test set-up shared by all tests: bpy runs as a module with its user resources isolated."""
import os
import tempfile

# Before anything imports bpy: never touch the developer's own Blender configuration.
os.environ.setdefault("BLENDER_USER_RESOURCES", tempfile.mkdtemp(prefix="sglf-blender-user-"))
