"""Operators: Bake SG Lightfield, Remove SG Bake."""
from __future__ import annotations

import bpy


class SGLF_OT_bake(bpy.types.Operator):
    """Bake the scene's glossy light field into spherical-Gaussian textures"""

    bl_idname = "sg_lightfield.bake"
    bl_label = "Bake SG Lightfield"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return context.scene is not None and not context.scene.sg_lightfield.is_baking

    def execute(self, context):
        # The pipeline stages (capture, render, train, apply) land in later issues; until then the
        # operator says so instead of pretending to bake.
        self.report({"WARNING"}, "SG Lightfield: the bake pipeline is not available in this build yet")
        return {"CANCELLED"}


class SGLF_OT_remove_bake(bpy.types.Operator):
    """Restore every material changed by an SG bake to its original node tree"""

    bl_idname = "sg_lightfield.remove_bake"
    bl_label = "Remove SG Bake"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        self.report({"INFO"}, "SG Lightfield: no baked materials to restore")
        return {"FINISHED"}


_classes = (SGLF_OT_bake, SGLF_OT_remove_bake)


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
