"""Scene settings of SG Lightfield (``scene.sg_lightfield``)."""
from __future__ import annotations

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, PointerProperty, StringProperty

PRESET_ITEMS = (
    ("DRAFT", "Draft", "Fast preview of the whole pipeline"),
    ("PREVIEW", "Preview", "Balanced quality for look development"),
    ("PRODUCTION", "Production", "Final quality"),
    ("CUSTOM", "Custom", "Set every knob yourself"),
)

DEVICE_ITEMS = (
    ("CPU", "CPU", "Train and render on the CPU"),
    ("CUDA", "CUDA / OptiX", "Render with OptiX and train with CUDA on an NVIDIA GPU; the bake stops with a message "
                             "when Cycles finds no OptiX device"),
)


# Blender 4.5+ asks path properties to declare that "//" (relative to the .blend) is meant; 4.2 lacks the option.
_BLEND_RELATIVE = {"PATH_SUPPORTS_BLEND_RELATIVE"} if bpy.app.version >= (4, 5, 0) else set()


class SGLightfieldSettings(bpy.types.PropertyGroup):
    preset: EnumProperty(name="Quality", items=PRESET_ITEMS, default="DRAFT")
    texel_density: FloatProperty(
        name="Texel Density", description="Light-field texels per metre of surface",
        default=8.0, min=1e-5, soft_min=0.1, soft_max=256.0, max=4096.0)
    lightfield_resolution: IntProperty(
        name="Light-Field Resolution", description="Octahedral light-field image size per texel: 8, 16, 32, 64 "
        "or 128 (a power of two)",
        default=16, min=8, max=128)
    samples: IntProperty(name="Samples", description="Cycles samples per light-field pixel",
                         default=16, min=1, max=65536)
    lightmap_samples: IntProperty(name="Lightmap Samples",
                                  description="Cycles samples per light-field pixel of objects that get only an "
                                  "irradiance lightmap (0: the same as Samples)", default=0, min=0, max=65536)
    sg_count_auto: BoolProperty(name="Automatic SG Count",
                                description="Give each glossy material the fewest SGs its roughness needs "
                                "(a measured rule, at most 16)", default=True)
    sg_count: IntProperty(name="SG Count", description="Spherical Gaussians per texel (at most 24 with an "
                          "irradiance detail above 1)", default=16, min=1, max=64)
    training_budget_s: FloatProperty(name="Training Budget", description="Seconds of training at most",
                                     default=300.0, min=1.0, subtype="TIME_ABSOLUTE", unit="TIME_ABSOLUTE")
    training_epochs: IntProperty(name="Training Epochs",
                                 description="Train exactly this many epochs, however long they take, instead of "
                                 "the time budget: the same bake on any machine (0: by the time budget)",
                                 default=0, min=0, soft_max=2000, max=1_000_000)
    lobe_refit_steps: IntProperty(name="Lobe Refit Steps",
                                  description="Steps refitting the SGs' axes, sharpness and amplitudes through the "
                                  "glossy shading after training (0: off; every preset uses 150)",
                                  default=150, min=0, soft_max=1000, max=100000)
    irradiance_detail: IntProperty(name="Irradiance Detail",
                                   description="Diffuse light at this many times the texel density, baked by Cycles "
                                   "(sharper lamp shadows; 1: the light fields' irradiance at the texels)",
                                   default=4, min=1, max=8)
    rough_materials: EnumProperty(
        name="Rough Materials", default="IRRADIANCE",
        description="Dielectrics of roughness 0.6 and above: what lights them in the baked scene",
        items=[("IRRADIANCE", "Irradiance Lightmap", "Bake their diffuse light from the same light field (no SGs)"),
               ("RENDERER", "Renderer's Own", "Leave them to the renderer's lighting (in EEVEE, its light probes)")])
    instance_copies: BoolProperty(
        name="Instances as Copies", default=False,
        description="Bake particle, vertex, face, nested and node-made instances as object copies that render in "
        "their place until Remove SG Bake (they carry no attribute for a lightmap of their own; off: they keep the "
        "renderer's lighting)")
    device: EnumProperty(name="Device", items=DEVICE_ITEMS, default="CPU")
    output_dir: StringProperty(name="Bake Directory", description="Where the bake writes its files",
                               default="//sg_bake", subtype="DIR_PATH",
                               options=_BLEND_RELATIVE)
    hair_network: EnumProperty(name="Hair Filter Network", default="LARGE",
                               description="Which shipped network filters the hair (when no model file is given)",
                               items=[("BASE", "Base", "The paper's Base U-Net: about half Large's time, higher error"),
                                      ("LARGE", "Large", "Twice the channels: about 1.5 s at 1024x1024 on 2 cores "
                                       "with 4 passes, the lowest error")])
    hair_model: StringProperty(name="Hair Filter Model", subtype="FILE_PATH", default="", options=_BLEND_RELATIVE,
                               description="ONNX hair filter to use; empty: the shipped network chosen above")
    hair_output_dir: StringProperty(name="Hair Output", subtype="DIR_PATH", default="//hair_filter",
                                    options=_BLEND_RELATIVE,
                                    description="Where Filter Hair writes filtered.exr, the PNGs and a summary")
    hair_background_samples: IntProperty(name="Background Samples", default=16, min=1, max=4096,
                                          description="Cycles samples for the scene behind the hair")
    hair_filter_passes: EnumProperty(name="Filter Passes", default="4",
                                     items=[("1", "1", "The image only (fastest)"),
                                            ("2", "2", "The image and its left-right mirror image, averaged"),
                                            ("4", "4", "The image and its three mirror images, averaged "
                                             "(least error; 4x the network time)")],
                                     description="Network passes over mirror images of the input, averaged")
    # Progress shown by the panel while a bake runs (written by the operator, read by the UI).
    is_baking: BoolProperty(default=False, options={"SKIP_SAVE"})
    progress: FloatProperty(default=0.0, min=0.0, max=1.0, subtype="FACTOR", options={"SKIP_SAVE"})
    status: StringProperty(default="", options={"SKIP_SAVE"})
    plan_text: StringProperty(default="", options={"SKIP_SAVE"})


def _root_package():
    """The extension's package (e.g. bl_ext.user_default.sg_lightfield); '' when imported as plain modules."""
    return __package__.rsplit(".", 1)[0] if __package__ and "." in __package__ else ""


class SGLightfieldPreferences(bpy.types.AddonPreferences):
    bl_idname = _root_package() or "sg_lightfield"
    torch_python: StringProperty(
        name="Python with torch", subtype="FILE_PATH", default="",
        description="Override: a Python 3.11 executable with torch 2.13 for training (Blender's own Python has no "
                    "torch); empty: the installed training runtime, or SGLF_TORCH_PYTHON")
    runtime_source: EnumProperty(
        name="Install From", default="AUTO",
        items=[("AUTO", "Automatic", "PyPI: CUDA wheels where an NVIDIA driver is found, CPU wheels otherwise"),
               ("PIP", "Pip's Configuration", "The package index pip is configured with on this computer (a mirror)"),
               ("WHEELS", "Folder of Wheels", "Offline: the torch, numpy, openexr, scipy and pillow wheels from a folder")])
    runtime_wheel_dir: StringProperty(name="Wheels", subtype="DIR_PATH", default="",
                                      description="Folder with the torch, numpy, openexr, scipy and pillow wheels (offline install)")

    def draw(self, context):
        from . import operators, training_runtime

        layout = self.layout
        box = layout.box()
        box.label(text="Training Runtime", icon="SCRIPT")
        user_dir = operators.runtime_user_dir()
        running = operators.runtime_install_running()
        installed = training_runtime.installed_runtime(user_dir)
        if running is not None:
            box.progress(factor=running.progress.fraction, type="BAR", text=running.progress.message)
            box.operator("sg_lightfield.cancel_training_runtime", icon="CANCEL")
        elif installed is not None:
            record = training_runtime.runtime_record(user_dir)
            box.label(text=f"Installed: torch {record.get('torch', '?')}"
                           + (" with CUDA" if record.get("cuda_available") else " (CPU)"), icon="CHECKMARK")
            box.label(text=str(installed))
            box.operator("sg_lightfield.remove_training_runtime", icon="TRASH")
        else:
            box.label(text="Not installed: training needs torch, which Blender's Python does not have", icon="INFO")
            box.prop(self, "runtime_source")
            if self.runtime_source == "WHEELS":
                box.prop(self, "runtime_wheel_dir")
            elif not bpy.app.online_access:
                box.label(text="Online access is off (Preferences > System > Network)", icon="ERROR")
            box.operator("sg_lightfield.install_training_runtime", icon="IMPORT")
        layout.prop(self, "torch_python")
        layout.label(text="Training runs in that Python as a separate process; rendering stays in Blender.")


_classes = (SGLightfieldSettings,)


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)
    if _root_package():
        bpy.utils.register_class(SGLightfieldPreferences)
    bpy.types.Scene.sg_lightfield = PointerProperty(type=SGLightfieldSettings)


def unregister():
    del bpy.types.Scene.sg_lightfield
    if _root_package():
        bpy.utils.unregister_class(SGLightfieldPreferences)
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
