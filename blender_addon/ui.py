"""Panels: Render properties and the 3D view sidebar show the same content."""
from __future__ import annotations

import os

import bpy


def draw_sg_lightfield(layout, context):
    settings = context.scene.sg_lightfield
    layout.use_property_split = True
    layout.use_property_decorate = False
    layout.prop(settings, "preset")
    col = layout.column(align=True)
    col.enabled = settings.preset == "CUSTOM"
    col.prop(settings, "texel_density")
    col.prop(settings, "lightfield_resolution")
    col.prop(settings, "samples")
    col.prop(settings, "lightmap_samples")
    col.prop(settings, "sg_count_auto")
    sub = col.column()
    sub.enabled = not settings.sg_count_auto
    sub.prop(settings, "sg_count")
    sub = col.column()
    sub.enabled = settings.training_epochs == 0
    sub.prop(settings, "training_budget_s")
    col.prop(settings, "lobe_refit_steps")
    col.prop(settings, "irradiance_detail")
    layout.prop(settings, "training_epochs")  # any preset: a fixed count instead of its time budget
    layout.prop(settings, "rough_materials")
    layout.prop(settings, "instance_copies")
    layout.prop(settings, "device")
    layout.prop(settings, "output_dir")
    layout.operator("sg_lightfield.show_plan", icon="INFO")
    if settings.plan_text:
        box = layout.box()
        for line in settings.plan_text.splitlines():
            box.label(text=line, icon="ERROR" if line.startswith("!") else "NONE")
    if settings.is_baking:
        layout.progress(factor=settings.progress, type="BAR", text=settings.status or "Baking")
        layout.operator("sg_lightfield.cancel", icon="CANCEL")
    elif settings.status:
        layout.label(text=settings.status)
    row = layout.row(align=True)
    row.operator("sg_lightfield.bake", icon="RENDER_STILL")
    row.operator("sg_lightfield.remove_bake", icon="LOOP_BACK")
    _draw_training_runtime(layout, context)
    layout.operator("sg_lightfield.open_report", icon="TEXT")
    if any(obj.type == "CURVES" for obj in context.scene.objects):
        box = layout.box()
        box.label(text="Hair Filter", icon="CURVES")
        box.prop(settings, "hair_network")
        box.prop(settings, "hair_model")
        box.prop(settings, "hair_output_dir")
        box.prop(settings, "hair_background_samples")
        box.prop(settings, "hair_filter_passes")
        box.operator("sg_lightfield.filter_hair", icon="RENDER_STILL")


def _draw_training_runtime(layout, context):
    """Where training will run, from cheap checks only (no subprocess in a draw call)."""
    from . import operators, training_runtime

    if training_runtime.torch_in_process():
        return
    running = operators.runtime_install_running()
    if running is not None:
        layout.progress(factor=running.progress.fraction, type="BAR", text=running.progress.message)
        layout.operator("sg_lightfield.cancel_training_runtime", icon="CANCEL")
        return
    override = operators.torch_python_preference(context) or os.environ.get(training_runtime.ENV_VAR, "")
    if override:
        layout.label(text=f"Training in {os.path.basename(override)} (override)", icon="SCRIPT")
    elif training_runtime.installed_runtime(operators.runtime_user_dir()) is not None:
        layout.label(text="Training in the installed runtime", icon="CHECKMARK")
    else:
        box = layout.box()
        box.label(text="Training needs torch, which Blender does not have", icon="INFO")
        box.operator("sg_lightfield.install_training_runtime", icon="IMPORT")


class SGLF_PT_render(bpy.types.Panel):
    bl_label = "SG Lightfield"
    bl_idname = "SGLF_PT_render"
    bl_space_type = "PROPERTIES"
    bl_region_type = "WINDOW"
    bl_context = "render"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        draw_sg_lightfield(self.layout, context)


class SGLF_PT_sidebar(bpy.types.Panel):
    bl_label = "SG Lightfield"
    bl_idname = "SGLF_PT_sidebar"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "SG Lightfield"

    def draw(self, context):
        draw_sg_lightfield(self.layout, context)


_classes = (SGLF_PT_render, SGLF_PT_sidebar)


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
