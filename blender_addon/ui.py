"""Panels: Render properties and the 3D view sidebar show the same content."""
from __future__ import annotations

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
    col.prop(settings, "training_budget_s")
    col.prop(settings, "lobe_refit_steps")
    layout.prop(settings, "rough_materials")
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
