"""Operators: Bake SG Lightfield (modal, cancellable), Cancel, Remove SG Bake, Show Plan, Open Report, Filter Hair;
Install / Cancel / Remove Training Runtime."""
from __future__ import annotations

import os
import sys

import bpy

from ..bake_directory.bake_plan import BakeCancelled, BakeInputError, BakeSettings
from . import apply as apply_module
from . import training_runtime
from .pipeline import BakeJob
from .scene_analysis import build_plan

_jobs = {}  # scene name -> running BakeJob (one bake per scene)
# The modal bake renders small tiles so one step (one Cycles call) lasts about a second: Esc is honoured
# between steps. ~0.25 M camera paths/s on 2 cores, half the pixels traced (the hemisphere cut).
MODAL_STEP_PATHS = 0.5e6
_cancel_requested = set()


def settings_from_panel(panel) -> BakeSettings:
    """The panel's knobs as BakeSettings: a named preset, or Custom with every knob as set. Training Epochs,
    rough materials, instance copies and the device apply to any preset."""
    device, rough_materials = panel.device.lower(), panel.rough_materials.lower()
    if panel.preset != "CUSTOM":
        return BakeSettings.from_preset(panel.preset.lower(), device=device, rough_materials=rough_materials,
                                        instance_copies=panel.instance_copies, training_epochs=panel.training_epochs)
    return BakeSettings.from_preset("draft", texel_density=panel.texel_density, rough_materials=rough_materials,
                                    instance_copies=panel.instance_copies,
                                    lightfield_resolution=panel.lightfield_resolution, samples=panel.samples,
                                    lightmap_samples=panel.lightmap_samples,
                                    sg_count=16 if panel.sg_count_auto else panel.sg_count,
                                    uniform_sg_count=not panel.sg_count_auto,
                                    training_budget_s=panel.training_budget_s,
                                    training_epochs=panel.training_epochs,
                                    lobe_refit_steps=panel.lobe_refit_steps, device=device,
                                    irradiance_detail=panel.irradiance_detail)


def settings_path(text: str, what: str) -> str:
    """An absolute path from a path setting ("//" = beside the .blend), or a BakeInputError saying why not."""
    path = text.strip()
    if not path:
        raise BakeInputError(f"set a {what}")
    if path.startswith("//") and not bpy.data.filepath:
        raise BakeInputError(f"save the .blend first, or choose an absolute {what} (it is relative: {path})")
    return os.path.normpath(bpy.path.abspath(path))


def bake_directory(panel) -> str:
    return settings_path(panel.output_dir, "bake directory")


def _root_package() -> str:
    return __package__.rsplit(".", 1)[0] if __package__ and "." in __package__ else ""


def addon_preferences(context):
    root = _root_package()
    addon = context.preferences.addons.get(root) if root else None
    return addon.preferences if addon is not None else None


def torch_python_preference(context) -> str:
    return getattr(addon_preferences(context), "torch_python", "")


def runtime_user_dir() -> str | None:
    """The extension's user directory, where Install Training Runtime puts its environment (None outside an
    installed extension, e.g. bpy as a module: there SGLF_TORCH_PYTHON or this Python's torch trains)."""
    root = _root_package()
    if not root.startswith("bl_ext."):
        return None
    return bpy.utils.extension_path_user(root, create=True)


def training_python(context, tried: list | None = None):
    """(python, where it was found) for training, or None; this process itself when it has torch."""
    if training_runtime.torch_in_process():
        return sys.executable, "this Python"
    return training_runtime.find_torch_python(torch_python_preference(context), runtime_user_dir(), tried)


def begin_modal(operator, context, interval_s: float):
    """Timer, modal handler and progress bar for a long operator; end_modal takes them down again."""
    wm = context.window_manager
    operator._timer = wm.event_timer_add(interval_s, window=context.window)
    wm.modal_handler_add(operator)
    wm.progress_begin(0, 100)
    return {"RUNNING_MODAL"}


def end_modal(operator, context):
    wm = context.window_manager
    wm.event_timer_remove(operator._timer)
    wm.progress_end()
    if context.workspace is not None:
        context.workspace.status_text_set(None)


class SGLF_OT_bake(bpy.types.Operator):
    """Bake the scene's glossy light field into spherical-Gaussian textures (Esc cancels)"""

    bl_idname = "sg_lightfield.bake"
    bl_label = "Bake SG Lightfield"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.name not in _jobs

    def _start(self, context):
        panel = context.scene.sg_lightfield
        settings = settings_from_panel(panel)
        tried = []
        if training_python(context, tried) is None:  # said at the click, not after the render
            raise BakeInputError(training_runtime.missing_torch_message(training_runtime.TORCH_HELP, tried))
        tile_megapixels = min(max(MODAL_STEP_PATHS / settings.samples / 1e6, 0.002), 4.0)
        job = BakeJob(context.scene, settings, bake_directory(panel), stages=("capture", "render", "train", "apply"),
                      tile_megapixels=tile_megapixels, torch_python=torch_python_preference(context),
                      runtime_dir=runtime_user_dir())
        _jobs[context.scene.name] = job
        _cancel_requested.discard(context.scene.name)
        panel.is_baking, panel.progress, panel.status = True, 0.0, job.plan.summary()
        return job

    def _finish(self, context, job, message, level="INFO"):
        panel = context.scene.sg_lightfield
        panel.is_baking = False
        panel.status = message
        _jobs.pop(context.scene.name, None)
        _cancel_requested.discard(context.scene.name)
        self.report({level}, f"SG Lightfield: {message}")
        applied = job.results.get("apply") if job is not None and level == "INFO" else None
        for warning in (applied or {}).get("warnings", ()):
            self.report({"WARNING"}, f"SG Lightfield: {warning}")

    def execute(self, context):
        """Blocking bake (scripts, bpy as a module): the same job the modal operator steps through."""
        try:
            job = self._start(context)
            job.run()
        except (BakeInputError, BakeCancelled, OSError) as exc:
            self._finish(context, None, str(exc), "ERROR")
            return {"CANCELLED"}
        self._finish(context, job, f"baked into {job.out_dir}")
        return {"FINISHED"}

    def invoke(self, context, event):
        try:
            self._start(context)
        except (BakeInputError, OSError) as exc:
            self._finish(context, None, str(exc), "ERROR")
            return {"CANCELLED"}
        return begin_modal(self, context, 0.05)

    def _stop_ui(self, context):
        end_modal(self, context)
        for area in context.screen.areas if context.screen else ():
            area.tag_redraw()

    def modal(self, context, event):
        job = _jobs.get(context.scene.name)
        if job is None:
            self._stop_ui(context)
            return {"CANCELLED"}
        if event.type == "ESC" or context.scene.name in _cancel_requested:
            job.cancel()
            self._stop_ui(context)
            self._finish(context, job, "cancelled; the scene is as it was, finished stages are kept", "WARNING")
            return {"CANCELLED"}
        if event.type != "TIMER":
            return {"PASS_THROUGH"}
        try:
            update = job.step()
        except (BakeInputError, BakeCancelled, OSError) as exc:
            job.cancel()
            self._stop_ui(context)
            self._finish(context, job, str(exc), "ERROR")
            return {"CANCELLED"}
        if update is None:
            self._stop_ui(context)
            self._finish(context, job, f"baked into {job.out_dir}")
            return {"FINISHED"}
        stage, fraction, message = update
        eta = job.eta_s()
        panel = context.scene.sg_lightfield
        panel.progress = fraction
        panel.status = f"{stage}: {message}" + (f" (ETA {eta:.0f} s)" if eta is not None else "")
        context.window_manager.progress_update(int(100 * fraction))
        if context.workspace is not None:
            context.workspace.status_text_set(f"SG Lightfield {100 * fraction:.0f}%: {panel.status}  (Esc cancels)")
        for area in context.screen.areas if context.screen else ():
            if area.type in ("PROPERTIES", "VIEW_3D"):
                area.tag_redraw()
        return {"RUNNING_MODAL"}


class SGLF_OT_cancel(bpy.types.Operator):
    """Stop the running bake; the scene stays as it was and finished stages are reused next time"""

    bl_idname = "sg_lightfield.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.name in _jobs

    def execute(self, context):
        _cancel_requested.add(context.scene.name)
        return {"FINISHED"}


class SGLF_OT_remove_bake(bpy.types.Operator):
    """Restore every material changed by an SG bake to its original and remove the bake's data"""

    bl_idname = "sg_lightfield.remove_bake"
    bl_label = "Remove SG Bake"
    bl_options = {"REGISTER", "UNDO"}

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.name not in _jobs

    def execute(self, context):
        restored = apply_module.remove_bake(context.scene)
        self.report({"INFO"}, f"SG Lightfield: {restored} material slot(s) restored" if restored
                    else "SG Lightfield: no baked materials to restore")
        return {"FINISHED"}


class SGLF_OT_show_plan(bpy.types.Operator):
    """Analyse the scene and show what the bake would model, and why"""

    bl_idname = "sg_lightfield.show_plan"
    bl_label = "Show Plan"

    def execute(self, context):
        panel = context.scene.sg_lightfield
        try:
            plan = build_plan(context.scene, settings_from_panel(panel))
        except BakeInputError as exc:
            panel.plan_text = f"! {exc}"
            self.report({"ERROR"}, f"SG Lightfield: {exc}")
            return {"CANCELLED"}
        lines = [plan.summary(), *plan.decisions(), *(f"! {w}" for w in plan.warnings)]
        panel.plan_text = "\n".join(lines)
        return {"FINISHED"}


class SGLF_OT_open_report(bpy.types.Operator):
    """Open the bake's report in the web browser or file viewer"""

    bl_idname = "sg_lightfield.open_report"
    bl_label = "Open Report"

    def execute(self, context):
        try:
            directory = bake_directory(context.scene.sg_lightfield)
        except BakeInputError as exc:
            self.report({"ERROR"}, str(exc))
            return {"CANCELLED"}
        for name in ("report.html", "report.json"):
            path = os.path.join(directory, name)
            if os.path.isfile(path):
                bpy.ops.wm.path_open(filepath=path)
                return {"FINISHED"}
        self.report({"WARNING"}, f"SG Lightfield: no report in {directory} yet; bake first")
        return {"CANCELLED"}


class SGLF_OT_filter_hair(bpy.types.Operator):
    """Render the scene's hair with a few stochastic samples and filter it with the hair U-Net (onnxruntime),
    composited over a Cycles render of the rest of the scene; the result opens as the image 'Filtered Hair'"""

    bl_idname = "sg_lightfield.filter_hair"
    bl_label = "Filter Hair"

    @classmethod
    def poll(cls, context):
        return context.scene is not None and context.scene.name not in _jobs

    def execute(self, context):
        from ..hair.filtering import HairFilterError
        from ..hair import blender_scene as hair
        panel = context.scene.sg_lightfield
        window_manager = context.window_manager
        window_manager.progress_begin(0, 100)

        def progress(fraction, message):
            window_manager.progress_update(int(100 * fraction))
            if context.workspace is not None:
                context.workspace.status_text_set(f"Filter Hair: {message}")

        try:
            out_dir = settings_path(panel.hair_output_dir, "hair output directory")
            model = settings_path(panel.hair_model, "hair filter model") if panel.hair_model.strip() else None
            result = hair.filter_hair(context.scene, out_dir, model_path=model,
                                      background_samples=panel.hair_background_samples,
                                      passes=int(panel.hair_filter_passes), network=panel.hair_network.lower(),
                                      progress=progress)
        except (BakeInputError, HairFilterError, OSError) as exc:
            self.report({"ERROR"}, f"Filter Hair: {exc}")
            return {"CANCELLED"}
        finally:
            window_manager.progress_end()
            if context.workspace is not None:
                context.workspace.status_text_set(None)
        path = str(result.paths["filtered_exr"])
        image = next((im for im in bpy.data.images if bpy.path.abspath(im.filepath) == path), None)
        if image is None:
            image = bpy.data.images.load(path)
            image.name = "Filtered Hair"
        else:
            image.reload()
        for warning in result.warnings:
            self.report({"WARNING"}, f"Filter Hair: {warning}")
        total = sum(result.seconds.values())
        self.report({"INFO"}, f"Filter Hair: {image.size[0]}x{image.size[1]} in {total:.1f} s "
                              f"(filter {result.seconds['filter']:.2f} s) -> {path}")
        return {"FINISHED"}


_runtime_install: list = []  # the running RuntimeInstall, at most one


def runtime_install_running():
    return _runtime_install[0] if _runtime_install and _runtime_install[0].running else None


class SGLF_OT_install_training_runtime(bpy.types.Operator):
    """Install torch and what training needs besides into a Python environment of the extension's own (asks first;
    Esc or Cancel stops it)"""

    bl_idname = "sg_lightfield.install_training_runtime"
    bl_label = "Install Training Runtime"
    bl_options = {"REGISTER"}

    @classmethod
    def poll(cls, context):
        return runtime_user_dir() is not None and runtime_install_running() is None

    def _plan(self, context):
        prefs = addon_preferences(context)
        source = getattr(prefs, "runtime_source", "AUTO").lower()
        return training_runtime.plan_install(runtime_user_dir(), source=source,
                                             wheel_dir=bpy.path.abspath(getattr(prefs, "runtime_wheel_dir", "")))

    def invoke(self, context, event):
        try:
            plan = self._plan(context)
        except training_runtime.RuntimeInstallError as error:
            self.report({"ERROR"}, f"SG Lightfield: {error}")
            return {"CANCELLED"}
        if plan.needs_network and not bpy.app.online_access:
            self.report({"ERROR"}, "SG Lightfield: Blender does not allow online access (Preferences > System > "
                                   "Network > Allow Online Access); allow it, or install from a folder of wheels")
            return {"CANCELLED"}
        return context.window_manager.invoke_confirm(self, event, title="Install Training Runtime",
                                                     message=f"Download and install {plan.description()}?",
                                                     confirm_text="Install")

    def execute(self, context):
        try:
            install = training_runtime.RuntimeInstall(self._plan(context), online_allowed=bpy.app.online_access)
        except training_runtime.RuntimeInstallError as error:
            self.report({"ERROR"}, f"SG Lightfield: {error}")
            return {"CANCELLED"}
        _runtime_install[:] = [install.start()]
        if context.window is None:  # a script or background Blender: no event loop to poll from, so wait here
            return self._finish(install.wait())
        return begin_modal(self, context, 0.25)

    def modal(self, context, event):
        install = _runtime_install[0] if _runtime_install else None
        if install is None:
            return {"CANCELLED"}
        if event.type == "ESC":
            install.cancel()
        if event.type not in {"TIMER", "ESC"}:
            return {"PASS_THROUGH"}
        progress = install.progress
        wm = context.window_manager
        wm.progress_update(int(100 * progress.fraction))
        if context.workspace is not None:
            context.workspace.status_text_set(f"Training runtime: {progress.message} ({100 * progress.fraction:.0f}%)")
        for window in wm.windows:
            for area in window.screen.areas:
                area.tag_redraw()
        if not progress.done:
            return {"RUNNING_MODAL"}
        end_modal(self, context)
        return self._finish(progress)

    def _finish(self, progress):
        if progress.error:
            self.report({"WARNING" if progress.error == "cancelled" else "ERROR"},
                        f"SG Lightfield: training runtime not installed: {progress.error}")
            return {"CANCELLED"}
        self.report({"INFO"}, f"SG Lightfield: training runtime {progress.message}")
        return {"FINISHED"}


class SGLF_OT_cancel_training_runtime(bpy.types.Operator):
    """Stop the training runtime's install; nothing of it is kept"""

    bl_idname = "sg_lightfield.cancel_training_runtime"
    bl_label = "Cancel Install"

    @classmethod
    def poll(cls, context):
        return runtime_install_running() is not None

    def execute(self, context):
        runtime_install_running().cancel()
        return {"FINISHED"}


class SGLF_OT_remove_training_runtime(bpy.types.Operator):
    """Delete the installed training runtime (the Python with torch in the extension's user directory)"""

    bl_idname = "sg_lightfield.remove_training_runtime"
    bl_label = "Remove Training Runtime"

    @classmethod
    def poll(cls, context):
        return runtime_user_dir() is not None and runtime_install_running() is None and \
            training_runtime.installed_runtime(runtime_user_dir()) is not None

    def invoke(self, context, event):
        return context.window_manager.invoke_confirm(self, event, title="Remove Training Runtime",
                                                     message="Delete the installed torch environment?",
                                                     confirm_text="Remove")

    def execute(self, context):
        training_runtime.remove_runtime(runtime_user_dir())
        self.report({"INFO"}, "SG Lightfield: training runtime removed")
        return {"FINISHED"}


_classes = (SGLF_OT_bake, SGLF_OT_cancel, SGLF_OT_remove_bake, SGLF_OT_show_plan, SGLF_OT_open_report,
            SGLF_OT_filter_hair, SGLF_OT_install_training_runtime, SGLF_OT_cancel_training_runtime,
            SGLF_OT_remove_training_runtime)


def register():
    for cls in _classes:
        bpy.utils.register_class(cls)


def unregister():
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
