"""The bake pipeline as a steppable job: the panel's modal operator and headless/bake.py drive the same code.

`BakeJob.step()` does one unit of work (the capture, one render tile, one training epoch or a poll of the
training worker, the apply) and returns (stage, overall fraction, message), or None when the job is done.
`BakeJob.cancel()` stops at once and leaves the scene as it was before the job: the stages already written
to the bake directory stay there and are reused by the next attempt (render tiles, training checkpoints).
"""
from __future__ import annotations

import json
import os
import queue
import subprocess
import tempfile
import threading
import time
from pathlib import Path

from ..bake_directory.bake_plan import STAGES as ALL_STAGES
from ..bake_directory.bake_plan import BakeCancelled, BakeInputError, write_json_atomic
from . import apply as apply_module
from . import lightmap_modifier
from .capture import LIGHTMAP_LAYER, TILE_KEYS, capture, lightmap_owners, remove_lightmap_uvs
from .render import render_steps
from .scene_analysis import build_plan, require_blender_version
from .stand_ins import copied, is_stand_in, remove_stand_ins
from .training_runtime import TORCH_HELP, find_torch_python, missing_torch_message, torch_in_process

ETA_MIN_PROGRESS = 0.01  # of a stage, before its own rate is trusted over the plan's estimate
REPO_ROOT = Path(__file__).resolve().parent.parent


class BakeJob:
    def __init__(self, scene, settings, out_dir, *, stages=ALL_STAGES, share=None, midpoints=0,
                 tile_megapixels=4.0, lightmap_uv="", pack_images=True, training="auto", torch_python="",
                 runtime_dir=None,
                 reference_samples=0, eevee_evaluation=True):
        """training: 'in_process' (this Python has torch), 'worker' (a subprocess), or 'auto'. reference_samples:
        the evaluate stage's path-traced reference spp (0: reference_samples_for the settings). eevee_evaluation:
        False evaluates with Cycles only (machines where EEVEE gets no OpenGL context)."""
        unknown = [s for s in stages if s not in ALL_STAGES]
        if unknown:
            raise BakeInputError(f"unknown stage(s) {unknown}")
        require_blender_version()
        self.scene, self.settings, self.out_dir = scene, settings, Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise BakeInputError(f"{out_dir}: exists and is not a directory")
        self.stages = [s for s in ALL_STAGES if s in stages]
        self.options = dict(share=share, midpoints=midpoints, tile_megapixels=tile_megapixels,
                            lightmap_uv=lightmap_uv, pack_images=pack_images, reference_samples=reference_samples,
                            eevee_evaluation=eevee_evaluation)
        self.training, self.torch_python, self.runtime_dir = training, torch_python, runtime_dir
        self.training_python = ""  # the Python the training worker ran in, and where it was found
        self.plan = build_plan(scene, settings)
        write_json_atomic(self.out_dir / "plan.json", self.plan.to_dict())
        self.estimates_s = self._stage_estimates_s()
        self._stage_clock: dict = {}  # stage -> (monotonic time, fraction) of its first and of its latest report
        self.results: dict = {}
        self.timings: dict = {}
        self.current_stage = ""
        self._worker = None
        self._applied = False
        self._captured_here = False
        self._steps = self._run()
        self.done = False

    # --- driving --------------------------------------------------------------------------------------
    def step(self):
        """One unit of work; returns (stage, overall fraction, message) or None when finished."""
        if self.done:
            return None
        try:
            return next(self._steps)
        except StopIteration:
            self.done = True
            return None

    def run(self, progress=None, should_cancel=lambda: False):
        """Drive the job to its end (headless, or the operator's blocking execute)."""
        while True:
            if should_cancel():
                self.cancel()
                raise BakeCancelled("bake cancelled")
            update = self.step()
            if update is None:
                return self.results
            if progress is not None:
                progress(*update)

    def cancel(self):
        """Stop now and leave the scene's data as it was before the job."""
        self._steps.close()  # closes the stage generators: temporary render scene removed, checkpoint saved
        if self._worker is not None:
            self._worker.terminate()
            self._worker.wait(timeout=10)
        if self.current_stage == "apply" and not self._applied:
            apply_module.remove_bake(self.scene)  # undo the slots a failed or stopped apply already switched
        if self._captured_here and not self._applied:
            self._restore_lightmaps()
        self._release_snapshot()
        self.done = True

    def _snapshot_lightmaps(self):
        """What capture will overwrite: each mesh's SGLightmap layer (when an earlier bake made one), each SG Lightmap
        UV modifier's carrier mesh and each object's tile properties, so a cancel can put back a previous bake
        exactly."""
        import numpy as np

        snapshot = {"meshes": {}, "objects": {}, "carriers": {}, "instance_tiles": {},
                    "stand_ins": {o.name for o in self.scene.objects if is_stand_in(o) or copied(o)}}
        for obj in lightmap_owners(self.scene):
            for kind, helper in (("carriers", lightmap_modifier.carrier_of(obj)),
                                 ("instance_tiles", lightmap_modifier.instance_tiles_of(obj))):
                if helper is not None:  # kept alive until the job ends: capture gives the helper a new mesh
                    helper.data.use_fake_user = True
                    snapshot[kind][obj.name] = helper.data
            snapshot["objects"][obj.name] = {k: list(obj[k]) for k in TILE_KEYS if k in obj}
            if obj.type != "MESH":
                continue
            layer = obj.data.uv_layers.get(LIGHTMAP_LAYER)
            if layer is not None and obj.data.name not in snapshot["meshes"]:
                uv = np.empty(len(obj.data.loops) * 2, np.float32)
                layer.uv.foreach_get("vector", uv)
                snapshot["meshes"][obj.data.name] = uv
        return snapshot

    def _restore_lightmaps(self):
        snapshot = self._lightmap_snapshot
        if not snapshot["meshes"] and not snapshot["carriers"] and not snapshot["instance_tiles"]:
            remove_lightmap_uvs(self.scene)  # nothing was baked before: the scene had no lightmap data at all
            return
        for obj in lightmap_owners(self.scene):
            saved = snapshot["objects"].get(obj.name, {})
            for key in TILE_KEYS:
                if key in saved:
                    obj[key] = saved[key]
                elif key in obj:
                    del obj[key]
            if obj.name in snapshot["carriers"] or obj.name in snapshot["instance_tiles"]:
                lightmap_modifier.restore_helpers(obj, snapshot["carriers"].get(obj.name),
                                                  snapshot["instance_tiles"].get(obj.name))
            else:
                lightmap_modifier.detach(obj)  # this job's capture added it
            if obj.type != "MESH":
                continue
            uv = snapshot["meshes"].get(obj.data.name)
            layer = obj.data.uv_layers.get(LIGHTMAP_LAYER)
            if uv is not None and layer is not None and len(uv) == 2 * len(obj.data.loops):
                layer.uv.foreach_set("vector", uv)
        remove_stand_ins(self.scene, keep=snapshot["stand_ins"])  # the ones this job's capture made

    # --- progress -------------------------------------------------------------------------------------
    def _stage_estimates_s(self) -> dict:
        """The plan's expected seconds of each stage this job runs (at least a second each)."""
        reference_samples, test_samples, evaluate_pixels = 0, 0, 0
        if "evaluate" in self.stages:
            from .evaluate import EVALUATE_RESOLUTION, EVALUATE_VIEWS
            reference_samples, test_samples = self._evaluation_samples()
            evaluate_pixels = EVALUATE_VIEWS * EVALUATE_RESOLUTION[0] * EVALUATE_RESOLUTION[1]
        estimates = self.plan.stage_estimates_s(reference_samples=reference_samples, evaluate_pixels=evaluate_pixels,
                                                test_samples=test_samples, with_eevee=self.options["eevee_evaluation"])
        return {stage: max(estimates[stage], 1.0) for stage in self.stages}

    def _overall(self, stage, fraction):
        """The whole job's fraction done, each stage weighted by its expected seconds; notes the stage's progress
        for eta_s."""
        now = time.monotonic()
        first, _ = self._stage_clock.get(stage, ((now, fraction), None))
        self._stage_clock[stage] = (first, (now, fraction))
        done = sum(self.estimates_s[s] for s in self.stages[:self.stages.index(stage)])
        total = sum(self.estimates_s.values()) or 1.0
        return min((done + self.estimates_s[stage] * fraction) / total, 1.0)

    def eta_s(self) -> float | None:
        """Seconds left: the current stage's rest at the rate it has run so far (the plan's estimate less the time
        it has run, until it has moved ETA_MIN_PROGRESS), plus the plan's estimates of the stages after it. Stages
        differ in speed per unit of progress (a render tile, a training epoch), so one rate for the whole bar misleads:
        the room Production bake's first glossy tiles projected 14872 s where 6560 s were left."""
        stage = self.current_stage
        if not stage:
            return None
        now = time.monotonic()
        (start, first_fraction), (latest, fraction) = self._stage_clock.get(stage, ((now, 0.0), (now, 0.0)))
        if fraction - first_fraction >= ETA_MIN_PROGRESS:  # its rate up to its latest report, counting down since
            rest = max((latest - start) * (1 - fraction) / (fraction - first_fraction) - (now - latest), 0.0)
        else:
            rest = max(self.estimates_s[stage] * (1 - first_fraction) - (now - start), 0.0)
        later = self.stages[self.stages.index(stage) + 1:]
        return rest + sum(self.estimates_s[s] for s in later)

    # --- stages ---------------------------------------------------------------------------------------

    def _run(self):
        for stage in self.stages:
            self.current_stage = stage
            start = time.perf_counter()
            result = yield from getattr(self, f"_{stage}")()
            self.results[stage] = result
            self.timings[stage] = time.perf_counter() - start
            yield stage, self._overall(stage, 1.0), f"{stage} done"
        self._release_snapshot()

    def _release_snapshot(self):
        """The previous bake's carrier meshes were held for a cancel; once the job is over they may go."""
        snapshot = getattr(self, "_lightmap_snapshot", None)
        snapshot = snapshot or {}
        for mesh in [*snapshot.get("carriers", {}).values(), *snapshot.get("instance_tiles", {}).values()]:
            try:
                mesh.use_fake_user = False
            except ReferenceError:
                pass
        lightmap_modifier.remove_orphans()

    def _capture(self):
        yield "capture", self._overall("capture", 0.0), "lightmap UVs and texel maps"
        self._lightmap_snapshot = self._snapshot_lightmaps()
        self._captured_here = True
        return capture(self.scene, self.plan, self.out_dir, lightmap_uv_layer=self.options["lightmap_uv"])

    def _stage_progress(self, stage, steps):
        """Relay a stage generator's (fraction, message) as overall progress; return its result."""
        try:
            while True:
                fraction, message = next(steps)
                yield stage, self._overall(stage, fraction), message
        except StopIteration as stop:
            return stop.value
        finally:
            steps.close()

    def _render(self):
        return (yield from self._stage_progress("render", render_steps(
            self.scene, self.plan, self.out_dir, share=self.options["share"], midpoints=self.options["midpoints"],
            max_tile_megapixels=self.options["tile_megapixels"])))

    def _train(self):
        mode = self.training
        if mode == "auto":
            mode = "in_process" if torch_in_process() else "worker"
        if mode == "in_process":
            from ..training.train_stage import train_steps

            return (yield from self._stage_progress("train", train_steps(self.out_dir, self.plan)))
        return (yield from self._train_worker())

    def _train_worker(self):
        """Training in a separate Python with torch; its JSON progress lines feed the progress bar."""
        tried = []
        found = find_torch_python(self.torch_python, self.runtime_dir, tried)
        if found is None:
            raise BakeInputError(missing_torch_message(TORCH_HELP, tried))
        python, self.training_python = found
        env = {**os.environ, "PYTHONPATH": str(REPO_ROOT) + os.pathsep + os.environ.get("PYTHONPATH", "")}
        errors = tempfile.TemporaryFile(mode="w+")  # a file, not a pipe: a chatty worker can never block on it
        self._worker = subprocess.Popen([python, "-m", "training.train_stage", "--out", str(self.out_dir), "--json"],
                                        stdout=subprocess.PIPE, stderr=errors, text=True, env=env,
                                        cwd=str(REPO_ROOT))
        lines: queue.Queue = queue.Queue()
        reader = threading.Thread(target=lambda: [lines.put(line) for line in self._worker.stdout], daemon=True)
        reader.start()
        result, fraction, message = None, 0.0, "starting the training worker"
        while self._worker.poll() is None or not lines.empty():
            try:
                event = json.loads(lines.get(timeout=0.1))
            except queue.Empty:
                yield "train", self._overall("train", fraction), message  # keeps the UI responsive
                continue
            except ValueError:
                continue
            if event.get("event") == "progress":
                fraction, message = max(fraction, event["fraction"]), event.get("message", "")
                yield "train", self._overall("train", fraction), message
            elif event.get("event") == "stage":
                result = event
        if self._worker.returncode != 0:
            errors.seek(0)
            error = errors.read().strip().splitlines()
            raise BakeInputError(error[-1].removeprefix("error: ") if error else "the training worker failed")
        errors.close()
        self._worker = None
        return result

    def _evaluation_samples(self) -> tuple[int, int]:
        """The evaluate stage's (reference, baked scene) spp: --reference-samples or the settings' rule."""
        from .evaluate import reference_samples_for, test_samples_for

        reference = self.options["reference_samples"] or reference_samples_for(self.plan.settings)
        return reference, test_samples_for(self.plan.settings, reference)

    def _evaluate(self):
        from .evaluate import evaluate_stage

        samples, test_samples = self._evaluation_samples()
        yield "evaluate", self._overall("evaluate", 0.0), \
            f"reference ({samples} spp) and baked ({test_samples} spp) renders"
        return evaluate_stage(self.scene, self.plan, self.out_dir, reference_samples=samples, test_samples=test_samples,
                              with_eevee=self.options["eevee_evaluation"])

    def _apply(self):
        yield "apply", self._overall("apply", 0.0), "materials"
        info = apply_module.apply_stage(self.scene, self.plan, self.out_dir, pack_images=self.options["pack_images"])
        self._applied = True
        return info
