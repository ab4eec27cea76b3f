"""Blender extension entry point: the repository root is the SG Lightfield extension package.

Blender imports this file as ``bl_ext.<repo>.sg_lightfield``; the add-on itself lives in
``blender_addon/``. Imports are deferred so that plain Python (pytest, headless tools) that
happens to import this package does not need bpy.
"""


def register():
    from .blender_addon import register as register_addon

    register_addon()


def unregister():
    from .blender_addon import unregister as unregister_addon

    unregister_addon()
