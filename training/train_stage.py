"""Train stage: fit SGs to the rendered light fields (and W_E) and write SG textures (needs torch, not bpy).

Runs in any Python with torch: in-process under bpy-as-a-module, or as a worker process
(`python -m training.train_stage --out DIR`) started by the add-on, whose own Python has no torch.
Checkpoints live in DIR/train/ and are loaded with weights_only=True; a second run resumes them.
"""
from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

if __name__ == "__main__" and __package__ in (None, "", "training"):  # started as a file or with -m
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
    from sg_launch import run_in_package

    run_in_package(__file__)

from ..bake_directory.bake_plan import (TRAINING_BUDGET_MAX_S, BakeCancelled, BakeInputError, BakePlan,  # noqa: E402
                                        drive)
from ..bake_directory.bake_report import save_png, update_report  # noqa: E402
from ..shaders.env_visibility import above_horizon_fraction  # noqa: E402
from ..bake_directory.lightfield_tiles import preview_mosaic, read_images  # noqa: E402
from ..bake_directory.sg_textures import bytes_per_texel, sg_texture_path, write_sg_texture, write_sh_texture  # noqa: E402
from ..bake_directory.texel_maps import channels, read_texel_maps, texels_of_objects  # noqa: E402


@dataclass
class TrainResult:
    seconds: float = 0.0
    metrics: dict = field(default_factory=dict)  # kind -> metrics
    epochs: dict = field(default_factory=dict)
    stopped_because: dict = field(default_factory=dict)
    bytes_per_texel: int = 0
    files: list = field(default_factory=list)


ENV_SGS_FILE = "env_sgs.json"
ENV_SG_COUNT = 16
FIXED_SG_COUNT = 12


def fit_environment_sgs(out_dir: Path, plan_hash: str, device: str = "cpu") -> dict:
    """The environment (env_radiance.exr, the whole sphere) as ENV_SG_COUNT global SGs (training/env_fit.py): the
    node group convolves them with each texel's warped NDF and multiplies by the texel's W_E. Written to
    DIR/env_sgs.json with the fit's errors over the map it fitted."""
    from ..bake_directory.exr_io import read_exr
    from .env_fit import fit_environment, fit_map
    from .sg_fit import error_metrics, reconstruct

    radiance = fit_map(read_exr(out_dir / "env_radiance.exr", channels=["R", "G", "B"])[0])
    sgs = fit_environment(radiance, ENV_SG_COUNT, device=device)
    axis, sharpness, amplitude = (np.array([sg[k] for sg in sgs]) for k in range(3))
    metrics = error_metrics(reconstruct(axis[None], sharpness[None], amplitude[None], radiance.shape[0]), radiance[None],
                            np.zeros((1, 3)))
    data_out = {"plan_hash": plan_hash, "sgs": [[a.tolist(), float(s), m.tolist()]
                                                for a, s, m in zip(axis, sharpness, amplitude)],
                "metrics": {k: round(v, 6) for k, v in metrics.items()}}
    from ..bake_directory.bake_plan import write_json_atomic

    write_json_atomic(out_dir / ENV_SGS_FILE, data_out)
    return data_out


def texel_material_ids(atlas, texels: np.ndarray) -> np.ndarray:
    """(T,) each texel's 1-based material id (0: none), as texels.json's tables number them."""
    return channels(atlas, "material_id")[texels[:, 0], texels[:, 1]].astype(np.int64)


def _per_texel(atlas, texel_info: dict, texels: np.ndarray, by_name: dict, default, dtype) -> np.ndarray:
    """(T,) the value by_name gives each texel's material (default for materials it does not name)."""
    by_id = np.full(len(texel_info["materials"]) + 1, default, dtype)
    for material in texel_info["materials"]:
        by_id[material["id"]] = by_name.get(material["name"], default)
    material_ids = texel_material_ids(atlas, texels)
    return by_id[np.clip(material_ids, 0, len(by_id) - 1)]


def texel_lobe_counts(atlas, texel_info: dict, texels: np.ndarray, plan: BakePlan, most: int) -> np.ndarray:
    """(T,) SGs each texel may use: its material's N from the plan (`most` for texels of materials that get no
    SGs: they sit beside glossy texels and bilinear lookups blend them in); a textured roughness's texels get what
    their measured roughness needs (auto_sg_count), up to the material's N."""
    from ..bake_directory.bake_plan import auto_sg_count

    glossy = [m for o in plan.baked_objects for m in o.materials if m.glossy]
    counts = _per_texel(atlas, texel_info, texels, {m.name: m.sg_count for m in glossy}, most, np.int64)
    textured = {m.name for m in glossy if "Roughness" in m.textured and not plan.settings.uniform_sg_count}
    if textured:
        ids = {m["id"] for m in texel_info["materials"] if m["name"] in textured}
        mine = np.isin(texel_material_ids(atlas, texels), list(ids))
        roughness = channels(atlas, "roughness")[texels[mine, 0], texels[mine, 1]]
        counts[mine] = np.minimum(counts[mine], [auto_sg_count(float(r), most) for r in roughness])
    return counts


def _error_members(atlas, texel_info: dict, texels, roughness, resolution: int, only=None):
    """Material name -> indices of its texels rough enough for the refits (glossy_refit.refit_min_roughness:
    sharper lobes see one pixel's constant radiance); of the materials named in `only` if given."""
    from .glossy_refit import refit_min_roughness

    material_ids = texel_material_ids(atlas, texels)
    resolved = roughness >= refit_min_roughness(resolution)
    members = {m["name"]: np.flatnonzero((material_ids == m["id"]) & resolved) for m in texel_info["materials"]
               if only is None or m["name"] in only}
    return {name: index for name, index in members.items() if len(index)}


def evenly(items: np.ndarray, count: int) -> np.ndarray:
    """At most `count` of `items`, evenly spaced from the first to the last."""
    return items[np.linspace(0, len(items) - 1, min(len(items), count)).astype(int)]


def shaded_errors(images, normals, axis, sharpness, amplitude, atlas, texel_info: dict, texels, roughness,
                  only=None, device="cpu") -> dict:
    """Material name -> relative RMSE between the node group's glossy of the SGs and the exact GGX reflection of
    the rendered light fields, on views the refit never fits (glossy_refit.shaded_error), over up to
    ERROR_TEXELS_PER_MATERIAL of the material's texels rough enough for the quadrature (of the materials named in
    `only` if given), on the training `device`."""
    from .glossy_refit import ERROR_TEXELS_PER_MATERIAL
    from .glossy_refit_torch import error_functions

    shaded_error = error_functions(device)[0]
    errors = {}
    for name, members in _error_members(atlas, texel_info, texels, roughness, images.shape[1], only).items():
        pick = evenly(members, ERROR_TEXELS_PER_MATERIAL)
        errors[name] = round(shaded_error(images[pick], normals[pick], axis[pick], sharpness[pick], amplitude[pick],
                                          roughness[pick]), 4)
    return errors


def interpolated_errors(images, normals, axis, sharpness, amplitude, atlas, texel_info: dict, texels,
                        roughness, only=None, device="cpu") -> dict:
    """Material name -> the same error halfway between atlas neighbours, with the SGs blended as the node group's
    bilinear lookup blends them (glossy_refit.interpolated_shaded_error), over up to ERROR_TEXELS_PER_MATERIAL
    neighbour pairs of the material's texels (of the materials named in `only` if given), on the training
    `device`."""
    from .glossy_refit import ERROR_TEXELS_PER_MATERIAL, atlas_neighbour_pairs
    from .glossy_refit_torch import error_functions

    interpolated_shaded_error = error_functions(device)[1]
    errors = {}
    for name, members in _error_members(atlas, texel_info, texels, roughness, images.shape[1], only).items():
        pairs = atlas_neighbour_pairs(texels[members])
        if len(pairs):
            pick = members[evenly(pairs, ERROR_TEXELS_PER_MATERIAL)]
            errors[name] = round(interpolated_shaded_error(images, normals, axis, sharpness, amplitude, roughness,
                                                           pick[:, 0], pick[:, 1]), 4)
    return errors


def keep_refit_where_better(trained: tuple, refitted: tuple, before: dict, after: dict, atlas, texel_info: dict,
                            texels, tolerance: float = 1.0):
    """Per material, the refitted values where they lower the held-out glossy error (`before` and `after` map
    material name -> error; with a tolerance > 1, where they raise it less than that factor), the trained ones
    elsewhere: (values, [materials kept], {material: error the refit had}); values are tuples of (T, ...) arrays.
    Where the GGX lobe is about a light-field pixel wide, a refit can fit the target's flaws (with the pixel-centre
    target it had before the pixel-integrated one (docs §28), Production spheres, R = 32: roughness 0.3 went 0.29 -> 0.34 on held-out views,
    FLIP 0.077 -> 0.092)."""
    material_ids = texel_material_ids(atlas, texels)
    result = tuple(np.array(value, copy=True) for value in trained)
    kept, reverted = [], {}
    for material in texel_info["materials"]:
        name = material["name"]
        if name not in before or name not in after:
            continue
        members = material_ids == material["id"]
        if after[name] < before[name] * tolerance:
            for value, new in zip(result, refitted):
                value[members] = new[members]
            kept.append(name)
        else:
            reverted[name] = after[name]
    return result, kept, reverted


def revert_where_worse_between_texels(trained, current, kept: list, between: dict, images, normals, axis,
                                      sharpness, atlas, texel_info: dict, texels, roughness, device="cpu"):
    """The amplitude refit is kept per material on the texels' own error (keep_refit_where_better); a lobe the
    views hardly see can still grow where the bilinear lookup blends normals (docs §19, before the ridge floor:
    an amplitude 1.02 -> 1317, error between texels 0.34 (the CNN's) -> 34.2 while the texels' own error fell).
    Per kept material, the trained amplitudes `trained` come back where `current` has a higher error between
    texels (`between`: material -> that error with `current`). Returns (amplitudes, still kept, {material: the
    error between texels the refit had}, the error between texels per material now)."""
    measured = [name for name in kept if name in between]
    if not measured:
        return current, kept, {}, between
    trained_between = interpolated_errors(images, normals, axis, sharpness, trained, atlas, texel_info, texels,
                                          roughness, only=measured, device=device)
    # keep_refit_where_better with the roles swapped: the trained amplitudes are taken where they are better.
    (result,), back, _ = keep_refit_where_better((current,), (trained,), {name: between[name] for name in measured},
                                                 trained_between, atlas, texel_info, texels)
    if not back:
        return current, kept, {}, between
    worse = {name: between[name] for name in back}
    return (result, [name for name in kept if name not in worse], worse,
            {name: trained_between[name] if name in worse else error for name, error in between.items()})


TORCH_MIN = (2, 6)  # fused Adam on the CPU (2.4) and torch.nn.utils.get_total_norm (2.6)


def check_torch_version(version: str) -> None:
    """One clear error where the Python that trains has a torch older than the training needs."""
    found = re.match(r"(\d+)\.(\d+)", version)
    if found is None or tuple(map(int, found.groups())) < TORCH_MIN:
        raise BakeInputError(f"torch {version} is older than {'.'.join(map(str, TORCH_MIN))}, which the training "
                             "needs; install the training runtime (add-on preferences) or torch 2.13 in that Python")


def _relayed(steps, progress):
    """Runs a generator that yields fractions done and returns a value: yields progress(fraction) for each
    fraction, returns the value."""
    while True:
        try:
            fraction = next(steps)
        except StopIteration as finished:
            return finished.value
        yield progress(fraction)


# Shares of the light field's progress bar: training, the amplitude refit, the lobe refit (when it runs).
PROGRESS_SHARES = (0.9, 0.1, 0.0)
PROGRESS_SHARES_WITH_LOBE_REFIT = (0.6, 0.05, 0.35)


def texel_roughness(atlas, texel_info: dict, texels: np.ndarray, plan: BakePlan) -> np.ndarray:
    """(T,) each texel's roughness: the capture's texel maps hold the plan's value for constant materials and the
    value measured over the texel for textured ones (blender_addon/surface_probe.py)."""
    return channels(atlas, "roughness")[texels[:, 0], texels[:, 1]].astype(np.float64)


def train_stage(out_dir, plan: BakePlan, *, progress=None, should_cancel=lambda: False, **options) -> TrainResult:
    """Train every kind the plan needs and write SG textures; resumable from DIR/train checkpoints."""
    return drive(train_steps(out_dir, plan, **options), progress, should_cancel,
                 "training cancelled; the checkpoint resumes it")


def train_steps(out_dir, plan: BakePlan, *, device: str | None = None, time_budget_s: float | None = None,
                encoder: str = "cnn", seed: int = 0):
    """The train stage as a generator: yields (fraction, message) after every epoch, returns TrainResult.
    Closing it early saves the checkpoint, so the next run continues the same curve. The benchmark's baselines
    at equal bytes: encoder 'fixed_sg' swaps in fixed-axis SG12 (written as the same SG textures), 'sh_l2' L2
    SH by least squares (an SH texture that apply shades through the SH variant of the node group). `seed` picks
    the CNN's initial weights and batch order (its own checkpoint): the benchmark's spread between trainings."""
    import torch

    from .baselines import bytes_per_texel_fixed_sg, bytes_per_texel_sh_l2, eval_sh, fit_fixed_sg, fit_sh_l2
    from .glossy_lobe_fit import LOBE_REFIT_GUARD_TOLERANCE, lobe_refit_min_roughness, lobe_refit_steps
    from .glossy_refit import REFIT_VIEW_AZIMUTHS, REFIT_VIEW_COSINES, refit_min_roughness
    from .glossy_refit_torch import amplitude_refit_steps, fitted_view_targets
    from .sg_fit import (LightFieldData, TrainConfig, Trainer, energy_kept, error_metrics,
                                 midpoint_parameters, pair_indices, reconstruct, unit_midpoint)

    start = time.perf_counter()
    out_dir = Path(out_dir)
    plan_hash = plan.stage_hash("train")
    atlas, texel_info = read_texel_maps(out_dir, plan.stage_hash("capture"))
    settings = plan.settings
    device = device or settings.device
    check_torch_version(torch.__version__)
    if device == "cuda" and not torch.cuda.is_available():
        raise BakeInputError("--device cuda: torch sees no CUDA device here; use --device cpu")
    sg_count = plan.max_sg_count or settings.sg_count or 16
    budget = time_budget_s if time_budget_s is not None else settings.training_budget_s
    epochs = settings.training_epochs if time_budget_s is None else 0  # a budget given here is the caller's choice
    # Only irradiance lightmaps (no object with SGs): apply integrates the light fields, nothing to fit.
    kinds = (["lightfield"] + (["env_visibility"] if plan.environment.iwev else [])) if plan.sg_objects else []
    if encoder not in ("cnn", "fixed_sg", "sh_l2"):
        raise ValueError(f"encoder {encoder!r} is not 'cnn', 'fixed_sg' or 'sh_l2'")
    if encoder == "sh_l2" and plan.environment.iwev:
        raise BakeInputError("the SH L2 baseline encodes light fields without environment visibility only")
    result = TrainResult()
    for k, kind in enumerate(kinds):
        texels, images = read_images(out_dir / kind, plan.stage_hash("render"))
        with_sgs = texels_of_objects(atlas, texel_info, texels, plan.sg_objects)  # lightmap-only texels get none
        texels, images = texels[with_sgs], images[with_sgs]
        if not len(texels):
            raise BakeInputError("no texel of a glossy material was rendered: nothing for the SGs to fit")
        normals = channels(atlas, "Ng.X", 3)[texels[:, 0], texels[:, 1]]
        roughness = texel_roughness(atlas, texel_info, texels, plan)
        if encoder == "fixed_sg":  # the production-lightmapper baseline, through the same textures and node group
            yield (k + 0.5) / len(kinds), f"{kind}: fixed SG{FIXED_SG_COUNT} amplitudes by NNLS"
            axes, shared_sharpness, amps = fit_fixed_sg(images, normals, FIXED_SG_COUNT)
            axis = np.broadcast_to(axes, amps.shape[:2] + (3,)).astype(np.float32)
            sharpness = np.full(amps.shape[:2], shared_sharpness, np.float32)
            amplitude = amps.astype(np.float32)
            epochs, stopped_because = 0, "least squares"
            texel_bytes = bytes_per_texel_fixed_sg(FIXED_SG_COUNT, images.shape[-1])  # axes and sharpness shared
        elif encoder == "sh_l2":
            yield (k + 0.5) / len(kinds), f"{kind}: L2 SH by least squares"
            coefficients = fit_sh_l2(images, normals).astype(np.float32)
            epochs, stopped_because = 0, "least squares"
            texel_bytes = bytes_per_texel_sh_l2(images.shape[-1])
        else:
            counts = texel_lobe_counts(atlas, texel_info, texels, plan, sg_count)
            data = LightFieldData.from_numpy(images, normals, device=device,
                                             lobe_counts=None if counts.min() == sg_count else counts)
            # By epochs, the time budget is the longest allowed: the epochs end it (or a loss plateau, which follows
            # the losses alone), not the machine's speed.
            config = TrainConfig(sg_count=sg_count, device=device, seed=seed,
                                 time_budget_s=TRAINING_BUDGET_MAX_S if epochs else budget / len(kinds))
            # Keyed by the rendered data, the SG counts and the seed, not the budget: a larger budget continues the
            # same curve. A count of epochs has its own: a longer run's checkpoint must not stand for a shorter one.
            counts_key = hashlib.sha256(counts.tobytes()).hexdigest()[:8]
            checkpoint = out_dir / "train" / (f"{kind}_{plan.stage_hash('render')}_n{sg_count}_{counts_key}"
                                              f"{f'_seed{seed}' if seed else ''}{f'_e{epochs}' if epochs else ''}.pt")
            trainer = Trainer(data, config, checkpoint=checkpoint)
            lobe_steps = settings.lobe_refit_steps if kind == "lightfield" else 0
            shares = PROGRESS_SHARES_WITH_LOBE_REFIT if lobe_steps else PROGRESS_SHARES
            training_share = shares[0] if kind == "lightfield" else 1.0  # of this kind's progress

            last_save = time.perf_counter()
            try:
                while True:
                    if epochs and trainer.state.epoch >= epochs:
                        state = trainer.state
                        state.stopped_because = "epochs"
                        break
                    state = trainer.train(epochs=1, save_checkpoint=False)
                    if time.perf_counter() - last_save > config.checkpoint_every_s:
                        trainer.save(trainer.checkpoint)
                        last_save = time.perf_counter()
                    if state.stopped_because != "epochs":
                        break
                    fraction = (state.epoch / epochs if epochs
                                else min(state.seconds[-1] / max(config.time_budget_s, 1e-9), 1.0))
                    yield (k + training_share * fraction) / len(kinds), \
                        f"{kind}: epoch {state.epoch}, loss {state.losses[-1]:.5f}"
            finally:
                trainer.save(trainer.checkpoint)
            axis, sharpness, amplitude = trainer.parameters_numpy()
            epochs, stopped_because = state.epoch, state.stopped_because
            texel_bytes = bytes_per_texel(sg_count, images.shape[-1])
            if kind == "lightfield":  # amplitudes fitted through the node group's glossy (glossy_refit)
                refit_start = time.perf_counter()
                before = shaded_errors(images, normals, axis, sharpness, amplitude, atlas, texel_info, texels,
                                       roughness, device=device)
                least = refit_min_roughness(images.shape[1])
                chosen = np.flatnonzero(roughness >= least)
                refitted = amplitude.copy()
                # the reflection both refits fit, once (most of their time on the CPU)
                yield (k + training_share) / len(kinds), f"{kind}: the reflection the refits fit"
                targets = np.zeros((len(images), len(REFIT_VIEW_COSINES) * REFIT_VIEW_AZIMUTHS, images.shape[-1]))
                needed = np.flatnonzero(roughness >= min(least, lobe_refit_min_roughness(images.shape[1]))
                                        if lobe_steps else roughness >= least)
                targets[needed] = fitted_view_targets(images[needed], normals[needed], roughness[needed], device)
                refitted[chosen] = yield from _relayed(
                    amplitude_refit_steps(images[chosen], normals[chosen], axis[chosen], sharpness[chosen],
                                          amplitude[chosen], roughness[chosen], counts[chosen], device=device,
                                          targets=targets[chosen]),
                    lambda fraction: ((k + training_share + shares[1] * fraction) / len(kinds),
                                      f"{kind}: amplitudes refitted through the glossy, {100 * fraction:.0f} %"))
                after = shaded_errors(images, normals, axis, sharpness, refitted, atlas, texel_info, texels, roughness,
                                      device=device)
                trained_amplitude = amplitude
                (amplitude,), kept, reverted = keep_refit_where_better((amplitude,), (refitted,), before, after, atlas,
                                                                       texel_info, texels)
                interpolated = interpolated_errors(images, normals, axis, sharpness, amplitude, atlas, texel_info,
                                                   texels, roughness, device=device)
                amplitude, kept, reverted_between, interpolated = revert_where_worse_between_texels(
                    trained_amplitude, amplitude, kept, interpolated, images, normals, axis, sharpness, atlas,
                    texel_info, texels, roughness, device)
                final_shaded_error = {name: after[name] if name in kept else error for name, error in before.items()}
                refit_report = {"seconds": round(time.perf_counter() - refit_start, 2), "texels": len(chosen),
                                "min_roughness": round(least, 3), "shaded_error_before": before,
                                "kept_for": kept, "reverted_for": reverted,
                                "reverted_between_texels_for": reverted_between}
                if lobe_steps:
                    lobe_start = time.perf_counter()
                    refitted = (axis.copy(), sharpness.copy(), amplitude.copy())
                    material_ids = texel_material_ids(atlas, texels)
                    rough_enough = np.flatnonzero(roughness >= lobe_refit_min_roughness(images.shape[1]))
                    groups = {m["name"]: np.intersect1d(rough_enough, np.flatnonzero(material_ids == m["id"]))
                              for m in texel_info["materials"]}
                    groups = {name: group for name, group in groups.items() if len(group)}
                    lobe_texels, done = sum(map(len, groups.values())), 0
                    for group in groups.values():
                        def lobe_progress(fraction, done=done, size=len(group)):
                            share = (done + size * fraction) / lobe_texels
                            return ((k + sum(shares[:2]) + shares[2] * share) / len(kinds),
                                    f"{kind}: lobes refitted through the glossy, {100 * share:.0f} %")

                        fitted = yield from _relayed(
                            lobe_refit_steps(images[group], normals[group], texels[group], axis[group],
                                             sharpness[group], amplitude[group], roughness[group],
                                             int(counts[group].max()), lobe_steps, device, targets[group]),
                            lobe_progress)
                        for value, new in zip(refitted, fitted):
                            value[group] = new
                        done += len(group)
                    lobe_after = interpolated_errors(images, normals, *refitted, atlas, texel_info, texels, roughness,
                                                     only=groups, device=device)
                    lobe_before = {name: error for name, error in interpolated.items() if name in groups}
                    (axis, sharpness, amplitude), lobe_kept, lobe_reverted = keep_refit_where_better(
                        (axis, sharpness, amplitude), refitted, lobe_before, lobe_after, atlas, texel_info, texels,
                        LOBE_REFIT_GUARD_TOLERANCE)
                    refit_report["lobes"] = {"seconds": round(time.perf_counter() - lobe_start, 2), "steps": lobe_steps,
                                             "texels": lobe_texels, "tolerance": LOBE_REFIT_GUARD_TOLERANCE,
                                             "min_roughness": round(lobe_refit_min_roughness(images.shape[1]), 3),
                                             "interpolated_error_before": lobe_before, "kept_for": lobe_kept,
                                             "reverted_for": lobe_reverted}
                    interpolated = {name: lobe_after[name] if name in lobe_kept else error
                                    for name, error in interpolated.items()}
                    if lobe_kept:
                        final_shaded_error.update(shaded_errors(images, normals, axis, sharpness, amplitude, atlas,
                                                                texel_info, texels, roughness, only=lobe_kept,
                                                                device=device))
        prediction = eval_sh(coefficients, images.shape[1]) if encoder == "sh_l2" else \
            reconstruct(axis, sharpness, amplitude, images.shape[1])
        metrics = error_metrics(prediction, images, normals)
        metrics["energy_kept"] = energy_kept(prediction, images, normals)  # the log loss's bias (sg_fit)
        if kind == "lightfield" and encoder != "sh_l2":
            if encoder == "cnn":  # the guards measured what they kept
                metrics["shaded_error"] = final_shaded_error
                metrics["interpolated_shaded_error"] = interpolated
                metrics["amplitude_refit"] = refit_report
            else:
                metrics["shaded_error"] = shaded_errors(images, normals, axis, sharpness, amplitude, atlas,
                                                        texel_info, texels, roughness, device=device)
                metrics["interpolated_shaded_error"] = interpolated_errors(images, normals, axis, sharpness, amplitude,
                                                                           atlas, texel_info, texels, roughness,
                                                                           device=device)
        picture = f"train_{kind}.png"  # rendered (left) | SG reconstruction (right), 16 texels each
        above = above_horizon_fraction(normals, images.shape[1]).reshape(prediction.shape[:3])[..., None]
        target_mosaic, predicted_mosaic = preview_mosaic(images), preview_mosaic(prediction * above)
        gap = np.ones((target_mosaic.shape[0], 2, 3))
        save_png(out_dir / picture, np.concatenate([target_mosaic, gap, predicted_mosaic], axis=1))
        result.files.append(picture)
        if kind == "lightfield" and (out_dir / "midpoints").is_dir():
            # Parameters averaged between the two neighbours (what bilinear filtering gives at the midpoint)
            # against the rendered, held-out midpoint light field.
            pairs, held_out = read_images(out_dir / "midpoints", plan.stage_hash("render"))
            a, b = pair_indices(texels, pairs)
            if encoder == "sh_l2":  # SH coefficients blend linearly
                prediction = eval_sh(0.5 * (coefficients[a] + coefficients[b]), images.shape[1])
            else:
                prediction = reconstruct(*midpoint_parameters(axis, sharpness, amplitude, a, b), images.shape[1])
            metrics["midpoint"] = error_metrics(prediction, held_out, unit_midpoint(normals[a], normals[b]))
        path = sg_texture_path(out_dir, kind)
        metadata = {"plan_hash": plan_hash, "kind": kind, "epochs": epochs, "encoder": encoder,
                    **({"seed": seed} if encoder == "cnn" and seed else {})}
        if encoder == "sh_l2":
            write_sh_texture(path, texels, coefficients, atlas.shape[:2], metadata)
        else:
            write_sg_texture(path, texels, axis, sharpness, amplitude, atlas.shape[:2], metadata)
        result.files.append(path.name)
        result.metrics[kind] = {k2: (round(v, 6) if isinstance(v, float) else v) for k2, v in metrics.items()}
        result.epochs[kind] = epochs
        result.stopped_because[kind] = stopped_because
        result.bytes_per_texel += texel_bytes
    if plan.environment.iwev:
        yield 0.99, "environment SGs"
        env = fit_environment_sgs(out_dir, plan_hash, device)
        result.files.append(ENV_SGS_FILE)
        result.metrics["environment"] = env["metrics"]
    result.seconds = time.perf_counter() - start
    update_report(out_dir, plan.stage_hash("capture"), timings_s={"train": result.seconds}, encoder=encoder,
                  sg_count=0 if encoder == "sh_l2" or not kinds else amplitude.shape[1],
                  bytes_per_texel=result.bytes_per_texel,
                  train={"metrics": result.metrics, "epochs": result.epochs, "stopped_because": result.stopped_because,
                         "device": device, "files": result.files})
    yield 1.0, "SG textures written"
    return result


def main(argv=None) -> int:
    """Worker entry point: train the bake in DIR from its plan.json (used by the add-on's worker process)."""
    p = argparse.ArgumentParser(prog="python -m training.train_stage")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--device", choices=("cpu", "cuda"))
    p.add_argument("--json", action="store_true")
    ns = p.parse_args(argv)
    try:
        plan = BakePlan.from_dict(json.loads((ns.out / "plan.json").read_text()))

        def progress(fraction, message):
            if ns.json:
                print(json.dumps({"event": "progress", "stage": "train", "fraction": round(fraction, 4),
                                  "message": message}), flush=True)

        result = train_stage(ns.out, plan, progress=progress, device=ns.device)
        print(json.dumps({"event": "stage", "stage": "train", "seconds": round(result.seconds, 3),
                          "metrics": result.metrics}), flush=True)
        return 0
    except (BakeInputError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    except (BakeCancelled, KeyboardInterrupt):
        print("error: cancelled; the checkpoint resumes training", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
