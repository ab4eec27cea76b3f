"""The bake plan and settings: plain dataclasses, JSON round trip, a content hash.

Pure Python (no bpy, no torch): the plan is the contract every stage reads from ``plan.json``.
"""
from __future__ import annotations

import hashlib
import json
import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

from .atomic import atomic_output

PLAN_VERSION = 1

# A material is 'glossy' (gets light-field SGs) below this Principled roughness. At 0.6 the warped
# GGX lobe (alpha = 0.36, sharpness 2/alpha^2/8 = 1.9) is ~40 degrees wide: its view dependence is
# well below what irradiance alone misses, so a rougher dielectric gets an irradiance lightmap (ROUGH_MATERIALS
# 'irradiance', the default) or keeps the renderer's own lighting ('renderer'). Rough metals have no diffuse
# to carry their light, so they stay glossy.
GLOSSY_ROUGHNESS_MAX = 0.6
# in a material plan's reason: a Principled coat stays in the baked copy (surface_shaders.LeafInputs.under_coat)
COAT_NOTE = "its coat is kept for the renderer to light, the bake lights what is below it"
# ... its alpha or Transparent BSDF cuts the baked lighting out; back faces keep the user's BSDF
# (surface_shaders.LeafInputs.see_through)
ALPHA_NOTE = "its alpha is kept (see-through parts show what is behind), its back faces are lit by the renderer"
# ... shader nodes the bake does not model, mixed beside its BSDFs, stay for the renderer to light
# (surface_shaders.RENDERER_LIT); a translucent surface is lit from both sides
RENDERER_LIT_NOTE = "kept for the renderer to light beside the baked BSDFs"
BACK_FACES_NOTE = "its back faces are lit by the renderer"
ROUGH_METALLIC_MAX = 0.5  # a rough material at least this metallic is shaded with SGs
ROUGH_MATERIALS = ("irradiance", "renderer")
LIGHTFIELD_RESOLUTIONS = (8, 16, 32, 64, 128)  # powers of two: training/sg_fit.SGEncoder pools them to 4 x 4

# Chosen from `python -m headless.bench --sections knobs` (spheres, one knob at a time from the old Draft, glossy
# FLIP against a 128 spp Cycles reference whose own noise floor there is 0.051): SGs at most 8 -> 16 was the best
# trade (glossy FLIP 0.120 -> 0.103 for +7 s: the per-material rule keeps rough materials at 8), 64 spp the next
# (0.112, +9 s), texel density 8 a small gain (0.114); R = 32 gained 0.002 for 4x the light-field pixels (R = 8 lost
# 0.014), and 15 s of training matched 60 s on 16 spp data (0.113 vs 0.120: longer fits the noise). Production keeps
# R = 32 and density 16 for scenes with finer lighting than spheres; on this 2-core CPU it is a long job (spheres:
# render ~40 min), on a GPU or a farm (--tile i/N) minutes.
# Adam steps of training/glossy_lobe_fit.py, in every preset. Spheres, the same CNN with and without it, FLIP of
# the roughness-0.5 sphere: Draft 0.102 -> 0.070 (+10 s), Preview 0.082 -> 0.066 (+30 s); 75 steps gave 0.076 and
# 0.071 (docs/design-additions.md section 27). Both refits reach roughness >= 0.28 at R = 16 (Draft, Preview) and
# >= 0.2 at R = 32; the lobe refit costs about 20 ms per texel at 16 SGs (section 29).
LOBE_REFIT_STEPS = 150
# Production gives every glossy material 16 SGs: on the Production spheres (same light fields) the per-material
# rule's 8 at roughness 0.4 / 0.5 cost FLIP 0.086 / 0.049 against 0.067 / 0.042 with 16 (section 23).
# Objects with only irradiance lightmaps need the light field's cosine-weighted mean, not its detail: Production
# renders them at 64 spp (R = 32: 4x Preview's samples per texel), not 256 (docs/design-additions.md section 23).
LIGHTMAP_SAMPLES_PRODUCTION = 64
# Diffuse light from a Cycles diffuse bake at this many times the texel density (capture stage, irradiance_detail.py)
# instead of the light fields' cosine-weighted mean at the texels: lamp shadows and contact shading at 4x finer
# pixels for a bake of a few seconds. Direct and indirect light are baked at the detail's resolution (at the texels'
# own, the light that passes a leaf card or a glass sphere blurred over a texel: demo:materials at Draft 0.0325 ->
# 0.0321, room 0.0561 -> 0.0551, docs/design-additions.md section 50), in one pass of this many samples per detail
# pixel: two passes (128 samples of direct light, 256 of indirect) cost a second Cycles sync per object, on
# demo:materials 16.9 s against 11.9 s, with more noise (the detail image's luminance against 8x the samples:
# relative RMSE 0.042 against 0.035) (section 51).
IRRADIANCE_DETAIL_SAMPLES = 256
IRRADIANCE_DETAIL_MAX = 8
# Camera paths per pixel sample of that pass (texels x detail^2 pixels), at the atlas render's rate, and the seconds
# each object adds (its Cycles sync, most of it the world's importance map: 4096 x 2048 for the shipped 1024 x 512
# HDRIs; its chart's margins). At Draft: demo:materials 3.3 M pixel samples and 7 objects in 10.9 s, demo:geometry
# 3.0 M and 29 objects in 28.7 s (room 10.4 M and 8 in 32.2 s: a closed room's paths are longer).
IRRADIANCE_DETAIL_PATHS_PER_SAMPLE = 0.45
IRRADIANCE_DETAIL_SYNC_S = 0.8
PRESETS = {
    "draft": dict(texel_density=4.0, lightfield_resolution=16, samples=16, sg_count=16, training_budget_s=30.0,
                  lobe_refit_steps=LOBE_REFIT_STEPS, lightmap_samples=0, irradiance_detail=4),
    "preview": dict(texel_density=8.0, lightfield_resolution=16, samples=64, sg_count=16, training_budget_s=120.0,
                    lobe_refit_steps=LOBE_REFIT_STEPS, lightmap_samples=0, irradiance_detail=4),
    "production": dict(texel_density=16.0, lightfield_resolution=32, samples=256, sg_count=16, uniform_sg_count=True,
                       training_budget_s=600.0, lobe_refit_steps=LOBE_REFIT_STEPS,
                       lightmap_samples=LIGHTMAP_SAMPLES_PRODUCTION, irradiance_detail=2),
}

# Camera paths per second of the atlas render on this machine class (2 cores), measured by `make bench` on
# the closed `room` (12 bounces): 0.25 M/s. Open scenes run faster (DESIGN section 4 saw 0.9 M/s).
ATLAS_RAYS_PER_SECOND_CPU = 0.25e6
TRAINING_BUDGET_MAX_S = 7 * 24 * 3600
TRAINING_EPOCHS_MAX = 1_000_000
# One planned texel through one CNN epoch at R = 16, on 2 CPU cores: demo:materials at Draft (808 planned texels, 1219
# captured), 88 epochs of each fit (light fields, environment visibility): the train stage took 73 s, against 76 s for
# the 30-s budget with its refits, so about 27 s of epochs. The cost grows with the light field's pixels.
TRAIN_S_PER_TEXEL_EPOCH_CPU = 1.9e-4
CYCLES_BYTES_PER_PIXEL = 64  # render buffers of one tile (combined pass, sample count, scratch)
# The other stages' cost on this machine class, measured on the room Production bake (docs section 31): capture
# 1.8 s and apply 9.5 s for 40379 texels; the refits after training 101 s (amplitudes) and 276 s (lobes, 150 steps)
# for 11283 glossy texels at 16 SGs. The evaluate stage path traces each view's reference (two halves) and its
# baked test at the reference samples, at the atlas render's rate; with the rest of its work, room measured 387 s
# and 418 s at 512 spp and 107 s at 128, i.e. 2.5 paths per pixel and reference sample.
CAPTURE_S_PER_TEXEL = 5e-5
APPLY_S_PER_TEXEL = 2.5e-4
AMPLITUDE_REFIT_S_PER_TEXEL = 0.009
LOBE_REFIT_S_PER_TEXEL_STEP = 0.025 / 150
# The evaluate stage per pixel, in atlas-render paths: per sample of the baked scene (its SG node groups included)
# and per reference sample (the original materials). Measured on `room` at Draft: 3.1 and 0.73 (spheres 0.69 and
# 0.23; materials 7.1 and 0.11, its node groups the largest). Docs §54.
EVALUATE_PATHS_PER_TEST_SAMPLE = 3.1
REFERENCE_PATHS_PER_SAMPLE = 0.73
# Two EEVEE processes (with the bake, alone), each baking its probes, compiling shaders and rendering both probe
# set-ups: about 100 s on `spheres` and `room` at Draft.
EEVEE_EVALUATE_S = 100.0


# Beyond this many SGs, with the irradiance detail image's lookup beside them, Cycles renders the baked copies of
# mixed, cut-out and emissive materials black (demo:materials, Cycles' evaluation: 20 and 24 SGs right at detail 4;
# 32 SGs black at detail 2 and 4, right at detail 1). The settings refuse the combination.
SG_COUNT_MAX_WITH_IRRADIANCE_DETAIL = 24


# The refits after training (training/glossy_refit.py, glossy_lobe_fit.py) work where the GGX lobe spans at least
# this many light-field pixels.
REFIT_LOBE_PIXELS = 0.36


def refit_min_roughness(resolution: int, lobe_pixels: float = REFIT_LOBE_PIXELS) -> float:
    """The least roughness the amplitude refit is used at: the GGX lobe (about alpha = roughness^2 radians wide)
    spans REFIT_LOBE_PIXELS light-field pixels (about sqrt(4 pi) / R radians). This gives 0.2 at R = 32, 0.28 at
    R = 16; sharper lobes see one pixel's constant radiance for most of what they reflect. With pixel-centre
    quadrature the bound had to be 0.5 pixels (0.24 at R = 32) and the target still aliased near it; the
    pixel-integrated target let it come down (docs/design-additions.md §28). The train stage keeps a material's
    refit only where it lowers the held-out error."""
    return float(math.sqrt(lobe_pixels * math.sqrt(4 * math.pi) / resolution))


# The light field leaves out one bounce of the kind the baked surface's own scattering is, so a path through the
# bake has the scene's bounce budget (render.py _RenderScene.configure). Rendered with the scene's own budget, the
# demo room's walls came out 4-9 % too bright and its Draft FLIP was 0.090; with one diffuse bounce fewer 0.065
# (docs/design-additions.md section 31). Part of the render stage's hash: light fields of the earlier rule are
# rendered again.
LIGHT_FIELD_BOUNCE_RULE = "one fewer of the baked surface's own scattering"


# Settings each stage's output depends on (cumulative: a stage also depends on the ones before it).
STAGES = ("capture", "render", "train", "apply", "evaluate")  # the pipeline's stages, in order
STAGE_SETTINGS = {
    "capture": {"texel_density"},
    "render": {"texel_density", "lightfield_resolution", "samples", "lightmap_samples"},
    "train": {"texel_density", "lightfield_resolution", "samples", "lightmap_samples", "sg_count", "uniform_sg_count",
              "training_budget_s", "training_epochs", "lobe_refit_steps"},
}
# The irradiance detail image is the capture's, in a file of its own that records the detail it was baked at: changing
# the detail bakes it again and applies again, and keeps the light fields and their training.
STAGE_SETTINGS["apply"] = STAGE_SETTINGS["evaluate"] = STAGE_SETTINGS["train"] | {"irradiance_detail"}


# Settings added after plan.json's first version, with the value that behaves as before they existed.
SETTINGS_ADDED_LATER = {"irradiance_detail": 1, "instance_copies": False, "training_epochs": 0}


class BakeInputError(ValueError):
    """The scene or the settings cannot be baked; the message says why and names the object."""


class BakeCancelled(Exception):
    """The user cancelled; the stage left nothing incomplete that looks complete."""


@dataclass
class BakeSettings:
    preset: str = "draft"
    texel_density: float = 4.0  # texels per metre
    lightfield_resolution: int = 16  # octahedral R
    samples: int = 16
    lightmap_samples: int = 0  # samples for the texels of objects with only irradiance lightmaps (0: `samples`)
    sg_count: int = 8  # the most SGs a glossy material gets (0 = 16); each gets what its roughness needs, up to it
    uniform_sg_count: bool = False  # every glossy material gets sg_count SGs, whatever its roughness
    training_budget_s: float = 60.0
    # > 0: each fit (light fields, environment visibility) trains exactly this many epochs, however long they take,
    # so a bake comes out the same on a busy or an idle machine (a farm's nodes); 0: for training_budget_s
    training_epochs: int = 0
    lobe_refit_steps: int = 0  # Adam steps refitting SG axes, sharpness and amplitudes through the glossy (0: off)
    rough_materials: str = "irradiance"  # rough dielectrics: an irradiance lightmap, or the renderer's own lighting
    device: str = "cpu"
    irradiance_detail: int = 1  # diffuse light at this many times the texel density (1: from the light fields)
    # Particle, vertex, face, nested and node-made instances carry no attribute of their own for a tile (or no object
    # to switch materials on): baked as object copies that render in their place (True), or left to the renderer.
    instance_copies: bool = False

    @property
    def lightmap_pass_samples(self) -> int:
        """Samples per light-field pixel of the texels whose objects get only irradiance lightmaps."""
        return self.lightmap_samples or self.samples

    @classmethod
    def from_preset(cls, name: str, **overrides):
        key = name.lower()
        if key not in PRESETS:
            raise BakeInputError(f"unknown preset {name!r}; choose one of {', '.join(PRESETS)}")
        values = {**PRESETS[key], **{k: v for k, v in overrides.items() if v is not None}}
        settings = cls(preset=key, **values)
        settings.validate()
        return settings

    def validate(self):
        checks = [
            (1e-5 <= self.texel_density <= 4096, f"texel density {self.texel_density} texels/m is outside 1e-5..4096"),
            (self.lightfield_resolution in LIGHTFIELD_RESOLUTIONS,
             f"light-field resolution {self.lightfield_resolution} is not one of "
             f"{', '.join(map(str, LIGHTFIELD_RESOLUTIONS))} (the SG encoder halves it down to 4 x 4)"),
            (1 <= self.samples <= 65536, f"samples {self.samples} is outside 1..65536"),
            (0 <= self.lightmap_samples <= 65536, f"lightmap samples {self.lightmap_samples} is outside 0 (= samples)"
                                                   "..65536"),
            (0 <= self.sg_count <= 64, f"SG count {self.sg_count} is outside 0 (= 16)..64"),
            (self.irradiance_detail == 1 or self.sg_count <= SG_COUNT_MAX_WITH_IRRADIANCE_DETAIL,
             f"SG count {self.sg_count} with irradiance detail {self.irradiance_detail}: beyond "
             f"{SG_COUNT_MAX_WITH_IRRADIANCE_DETAIL} SGs beside the detail image Cycles renders the baked copies of "
             f"mixed, cut-out and emissive materials black; use at most {SG_COUNT_MAX_WITH_IRRADIANCE_DETAIL} SGs or "
             "irradiance detail 1"),
            (1 <= self.training_budget_s <= TRAINING_BUDGET_MAX_S,
             f"training budget {self.training_budget_s} s is outside 1 s..7 days"),
            (0 <= self.training_epochs <= TRAINING_EPOCHS_MAX,
             f"training epochs {self.training_epochs} is outside 0 (= by the time budget)..{TRAINING_EPOCHS_MAX}"),
            (0 <= self.lobe_refit_steps <= 100_000, f"lobe refit steps {self.lobe_refit_steps} is outside 0..100000"),
            (self.device in ("cpu", "cuda"), f"device {self.device!r} is not 'cpu' or 'cuda'"),
            (1 <= self.irradiance_detail <= IRRADIANCE_DETAIL_MAX,
             f"irradiance detail {self.irradiance_detail} is outside 1 (from the light fields).."
             f"{IRRADIANCE_DETAIL_MAX}"),
            (self.rough_materials in ROUGH_MATERIALS,
             f"rough materials {self.rough_materials!r} is not one of {', '.join(ROUGH_MATERIALS)}"),
        ]
        for ok, message in checks:
            if not ok:
                raise BakeInputError(message)


@dataclass
class MaterialPlan:
    name: str
    roughness: float
    metallic: float
    glossy: bool
    sg_count: int
    reason: str
    irradiance_only: bool = False  # baked as an irradiance lightmap: diffuse from the light field, no SGs
    textured: list[str] = field(default_factory=list)  # BSDF inputs driven by links: measured per texel at capture

    @property
    def baked(self) -> bool:
        return self.glossy or self.irradiance_only


@dataclass
class ObjectPlan:
    name: str
    area_m2: float
    texels: int
    bake_lightfield: bool
    materials: list[MaterialPlan] = field(default_factory=list)
    reason: str = ""
    geometry: str = "mesh"  # what its evaluated surface is: "mesh", "mesh + Bevel, Array", "text", "curve", ...
    # An instance: the object that instances it, the instanced object and its place among that instancer's instances
    # (scene_analysis.instances_by_instancer's order); empty / -1 for an object of the scene itself.
    instancer: str = ""
    source: str = ""
    instance: int = -1


@dataclass
class EnvironmentPlan:
    present: bool
    kind: str  # none | color | hdri
    chromatic: bool
    iwev: bool
    iwev_channels: int
    reason: str


@dataclass
class BakePlan:
    scene: str
    settings: BakeSettings
    objects: list[ObjectPlan]
    environment: EnvironmentPlan
    lamps: list[str]
    emissive_objects: list[str]
    hair_objects: list[str]
    warnings: list[str] = field(default_factory=list)
    version: int = PLAN_VERSION

    @property
    def baked_objects(self):
        return [o for o in self.objects if o.bake_lightfield]

    @property
    def texels(self) -> int:
        return sum(o.texels for o in self.baked_objects)

    @property
    def sg_objects(self) -> list[str]:
        """Objects whose texels get SGs: those with a glossy material (a rough material beside a glossy one keeps
        SGs, as bilinear lookups blend neighbouring texels). The others' texels hold only irradiance."""
        return [o.name for o in self.baked_objects if any(m.glossy for m in o.materials)]

    @property
    def irradiance_only_materials(self) -> list[str]:
        return sorted({m.name for o in self.baked_objects for m in o.materials if m.irradiance_only})

    @property
    def max_sg_count(self) -> int:
        return max((m.sg_count for o in self.baked_objects for m in o.materials if m.glossy), default=0)

    @property
    def glossy_bounce_objects(self) -> list[str]:
        """Baked objects whose light field leaves out a glossy bounce instead of a diffuse one: every baked material
        on them is at least ROUGH_METALLIC_MAX metallic, so their own scattering in the bake is mostly glossy."""
        return [o.name for o in self.baked_objects
                if any(m.baked for m in o.materials)
                and all(m.metallic >= ROUGH_METALLIC_MAX for m in o.materials if m.baked)]

    @property
    def lightmap_only_objects(self) -> list[ObjectPlan]:
        """Baked objects without SGs: their texels are rendered at the settings' lightmap_pass_samples."""
        with_sgs = set(self.sg_objects)
        return [o for o in self.baked_objects if o.name not in with_sgs]

    @property
    def lightmap_only_texels(self) -> int:
        return sum(o.texels for o in self.lightmap_only_objects)

    @property
    def lightfield_texels(self) -> int:
        """Texels the render stage gives light fields: with an irradiance detail image, only those of objects with
        SGs (the image holds every surface's diffuse light)."""
        return self.texels - self.lightmap_only_texels if self.settings.irradiance_detail > 1 else self.texels

    def render_estimate_s(self) -> float:
        r, settings = self.settings.lightfield_resolution, self.settings
        lightmap = self.lightmap_only_texels if settings.irradiance_detail <= 1 else 0
        pixel_samples = ((self.lightfield_texels - lightmap) * settings.samples
                         + lightmap * settings.lightmap_pass_samples)
        rays = r * r * pixel_samples / 2  # upper hemisphere only
        if self.environment.iwev:
            rays += self.lightfield_texels * r * r / 2  # one primary ray per pixel for L_E * V
        return rays / ATLAS_RAYS_PER_SECOND_CPU

    def irradiance_detail_estimate_s(self) -> float:
        """The capture's Cycles diffuse bake of the irradiance detail image (0 when the detail is 1)."""
        detail = self.settings.irradiance_detail
        if detail <= 1 or not self.baked_objects:
            return 0.0
        return (self.texels * detail * detail * IRRADIANCE_DETAIL_SAMPLES * IRRADIANCE_DETAIL_PATHS_PER_SAMPLE
                / ATLAS_RAYS_PER_SECOND_CPU + IRRADIANCE_DETAIL_SYNC_S * len(self.baked_objects))

    def training_estimate_s(self) -> float:
        """The CNN's training: the time budget, or its epochs' expected time on 2 CPU cores."""
        epochs = self.settings.training_epochs
        if not epochs:
            return self.settings.training_budget_s
        fits = 1 + int(self.environment.iwev)
        scale = (self.settings.lightfield_resolution / 16) ** 2
        texels = self.texels - self.lightmap_only_texels  # the texels that get SGs
        return fits * epochs * texels * TRAIN_S_PER_TEXEL_EPOCH_CPU * scale

    def stage_estimates_s(self, reference_samples: int = 0, evaluate_pixels: int = 0,
                          test_samples: int = 0, with_eevee: bool = True) -> dict[str, float]:
        """Expected seconds of each stage on 2 CPU cores: the progress bar's weights, and the ETA of the stages not
        begun. evaluate_pixels: the evaluate stage's pixels over all its views; test_samples: the baked scene's
        render's samples there."""
        least = refit_min_roughness(self.settings.lightfield_resolution)
        refitted = sum(o.texels for o in self.baked_objects
                       if any(m.glossy and (m.roughness >= least or "Roughness" in m.textured) for m in o.materials))
        refits = refitted * (AMPLITUDE_REFIT_S_PER_TEXEL + LOBE_REFIT_S_PER_TEXEL_STEP * self.settings.lobe_refit_steps)
        return {"capture": 0.5 + CAPTURE_S_PER_TEXEL * self.texels + self.irradiance_detail_estimate_s(),
                "render": self.render_estimate_s(),
                "train": self.training_estimate_s() + refits,
                "apply": 1.0 + APPLY_S_PER_TEXEL * self.texels,
                "evaluate": EEVEE_EVALUATE_S * with_eevee + evaluate_pixels / ATLAS_RAYS_PER_SECOND_CPU
                * (EVALUATE_PATHS_PER_TEST_SAMPLE * test_samples + REFERENCE_PATHS_PER_SAMPLE * reference_samples)}

    def sharper_than_resolved(self) -> list[tuple[str, float]]:
        """(name, roughness) of the glossy materials with a constant roughness whose GGX lobe is narrower than the
        light field resolves (refit_min_roughness): sorted by name. A textured roughness is measured per texel only
        at capture, so it is not judged here."""
        least = refit_min_roughness(self.settings.lightfield_resolution)
        return sorted({(m.name, m.roughness) for o in self.baked_objects for m in o.materials
                       if m.glossy and "Roughness" not in m.textured and m.roughness < least})

    def decisions(self) -> list[str]:
        """What the bake models and why, one line each: what the CLI prints, the panel and the report show."""
        lines = [f"{o.name}: {'bake' if o.bake_lightfield else 'skip'} ({o.reason}; {o.texels} texels"
                 + ("" if o.geometry == "mesh" else f"; {o.geometry}") + ")" for o in self.objects]
        glossy = {m.name: f"up to {m.sg_count} (per texel, its textured roughness)"
                  if "Roughness" in m.textured and not self.settings.uniform_sg_count else m.sg_count
                  for o in self.baked_objects for m in o.materials if m.glossy}
        if glossy:
            rule = ("every glossy material the same (uniform)" if self.settings.uniform_sg_count else
                    f"the fewest within {100 * SG_COUNT_ERROR_BUDGET:.0f} % of 16 SGs at its roughness (measured), at most "
                    f"{self.settings.sg_count or 16}")
            lines.append("SGs per material: " + ", ".join(f"{k} {v}" for k, v in sorted(glossy.items()))
                         + f" ({rule})")
        if self.irradiance_only_materials:
            lines.append("irradiance lightmap only (rough, no SGs): " + ", ".join(self.irradiance_only_materials))
        sharp = self.sharper_than_resolved()
        if sharp:
            resolution = self.settings.lightfield_resolution
            finer = next((r for r in LIGHTFIELD_RESOLUTIONS if r > resolution), None)
            lines.append(f"sharper than {resolution}x{resolution} light fields resolve (roughness below "
                         f"{refit_min_roughness(resolution):.2f}), their reflections come out blurred: "
                         + ", ".join(f"{name} at {roughness:.2f}" for name, roughness in sharp)
                         + (f" (a light-field resolution of {finer} resolves down to {refit_min_roughness(finer):.2f}, "
                            "at about 3x the render time and 4x the training time)" if finer else ""))
        left = sorted({m.name for o in self.objects for m in o.materials if m.reason.startswith("left to the renderer")})
        if left:
            lines.append("left to the renderer (reasons above): " + ", ".join(left))
        for note, heading in (
                (COAT_NOTE, "baked below their coat, the coat kept for the renderer to light"),
                (ALPHA_NOTE, "baked with their alpha kept, back faces lit by the renderer"),
                (RENDERER_LIT_NOTE, "baked beside shaders the renderer lights (translucent, sheen, ...)")):
            names = sorted({m.name for o in self.objects for m in o.materials if note in m.reason})
            if names:
                lines.append(f"{heading}: " + ", ".join(names))
        if self.lightmap_only_texels and self.settings.irradiance_detail > 1:
            names = ", ".join(o.name for o in self.lightmap_only_objects)
            lines.append(f"objects with lightmaps only ({names}): no light fields (the irradiance detail image holds "
                         "their light)")
        elif self.lightmap_only_texels and self.settings.lightmap_pass_samples != self.settings.samples:
            names = ", ".join(o.name for o in self.lightmap_only_objects)
            lines.append(f"light fields of objects with lightmaps only ({names}): "
                         f"{self.settings.lightmap_pass_samples} samples per pixel (irradiance needs their mean), "
                         f"the others {self.settings.samples}")
        if self.baked_objects:
            detail = self.settings.irradiance_detail
            lines.append(f"diffuse light: a Cycles diffuse bake at {detail}x the texel density "
                         f"({detail * self.settings.texel_density:g} pixels/m, {IRRADIANCE_DETAIL_SAMPLES} samples of "
                         "direct and indirect light)"
                         if detail > 1 else "diffuse light: the light fields' irradiance at the texels")
            metals = self.glossy_bounce_objects
            lines.append("light fields rendered with one diffuse bounce fewer than the scene allows"
                         + (f" (metals {', '.join(metals)}: one glossy bounce fewer)" if metals else "")
                         + ": the baked surface's own scattering is the path's last")
        lines.append(f"environment: {self.environment.reason}")
        if self.lamps or self.emissive_objects:
            lines.append(f"light sources: lamps {self.lamps or 'none'}, "
                         f"emissive meshes {self.emissive_objects or 'none'}")
        lines.append("hair: " + (f"filter offered for {self.hair_objects}" if self.hair_objects else "no hair curves"))
        return lines

    def memory_estimate_mb(self, tile_megapixels: float = 4.0) -> dict:
        """Disk for the bake directory and peak RAM (training holds every light field as float32)."""
        r2 = self.settings.lightfield_resolution ** 2
        passes = 3 if self.environment.iwev else 1  # light field, W_E, L_E*V
        rendered, detail = self.lightfield_texels, self.settings.irradiance_detail
        disk = rendered * r2 * 3 * 2 * passes + self.texels * 2 * 7 * max(self.max_sg_count, 1) * passes
        if detail > 1:  # the irradiance detail image, half RGB
            disk += self.texels * detail * detail * 3 * 2
        ram = rendered * r2 * 3 * 4 + tile_megapixels * 1e6 * CYCLES_BYTES_PER_PIXEL
        return {"disk_mb": round(disk / 1e6, 1), "ram_mb": round(ram / 1e6, 1)}

    def summary(self) -> str:
        glossy = sum(any(m.glossy for m in o.materials) for o in self.baked_objects)
        rough = len(self.baked_objects) - glossy
        parts = [f"{glossy} glossy object{'s' if glossy != 1 else ''}"
                 + (f" + {rough} with an irradiance lightmap" if rough else ""),
                 f"{self.max_sg_count} SGs" if glossy else "no light-field SGs",
                 f"env visibility {'on (' + ('RGB' if self.environment.iwev_channels == 3 else 'mono') + ')' if self.environment.iwev else 'off'}",
                 f"hair {'offered' if self.hair_objects else 'off'}",
                 f"{self.texels} texels", f"render ~{self.render_estimate_s():.0f} s",
                 (f"training {self.settings.training_epochs} epochs (~{self.training_estimate_s():.0f} s)"
                  if self.settings.training_epochs else f"training <= {self.settings.training_budget_s:.0f} s")
                 + (f" + {self.settings.lobe_refit_steps} lobe-refit steps" if self.settings.lobe_refit_steps else "")]
        memory = self.memory_estimate_mb()
        parts.append(f"~{memory['disk_mb']:g} MB on disk, ~{memory['ram_mb']:g} MB RAM")
        return ", ".join(parts)

    def to_dict(self) -> dict:
        data = asdict(self)
        data["summary"] = self.summary()
        data["texels"] = self.texels
        data["render_estimate_s"] = round(self.render_estimate_s(), 3)
        data["memory_estimate_mb"] = self.memory_estimate_mb()
        data["decisions"] = self.decisions()
        data["hash"] = self.content_hash()
        return data

    def content_hash(self) -> str:
        """sha256 of the whole plan (settings, objects, environment, lights): plan.json's tamper check. A setting
        added since plan.json's first version counts only away from the value that keeps the older behaviour, so a
        plan.json written before it still reads as intact."""
        data = asdict(self)
        for key, value in SETTINGS_ADDED_LATER.items():
            if data["settings"].get(key) == value:
                del data["settings"][key]
        payload = json.dumps(data, sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(payload).hexdigest()[:16]

    def stage_hash(self, stage: str) -> str:
        """sha256 of what one stage's output depends on. Stages store it and refuse inputs made for another
        plan, while a change that only later stages see (say the training budget) keeps earlier outputs."""
        if stage not in STAGE_SETTINGS:
            raise ValueError(f"unknown stage {stage!r}")
        data = asdict(self)
        data["settings"] = {k: v for k, v in data["settings"].items() if k in STAGE_SETTINGS[stage]}
        if not data["settings"].get("training_epochs"):  # by time: hashed as before the setting existed
            data["settings"].pop("training_epochs", None)
        if stage in ("capture", "render"):
            for obj in data["objects"]:
                for material in obj["materials"]:
                    material.pop("sg_count", None)
        if stage != "capture":
            data["light_field_bounce_rule"] = LIGHT_FIELD_BOUNCE_RULE
            if self.settings.irradiance_detail > 1 and self.lightmap_only_objects:
                data["lightmap_only_light_fields"] = False  # they get no light fields then (render.py)
        data.pop("warnings", None)  # prose: rewording it must not invalidate finished renders
        data["environment"].pop("reason", None)
        for obj in data["objects"]:
            obj.pop("reason", None)
            for material in obj["materials"]:
                material.pop("reason", None)
        payload = json.dumps([stage, data], sort_keys=True, separators=(",", ":")).encode()
        return hashlib.sha256(payload).hexdigest()[:16]

    @classmethod
    def from_dict(cls, data: dict) -> "BakePlan":
        objects = [ObjectPlan(**{**o, "materials": [MaterialPlan(**mp) for mp in o["materials"]]})
                   for o in data["objects"]]
        plan = cls(scene=data["scene"], settings=BakeSettings(**data["settings"]), objects=objects,
                   environment=EnvironmentPlan(**data["environment"]), lamps=list(data["lamps"]),
                   emissive_objects=list(data["emissive_objects"]), hair_objects=list(data["hair_objects"]),
                   warnings=list(data.get("warnings", [])), version=data.get("version", PLAN_VERSION))
        if "hash" in data and data["hash"] != plan.content_hash():
            raise BakeInputError("plan.json was edited or is corrupt: its hash does not match its content")
        return plan


def drive(steps, progress=None, should_cancel=lambda: False, cancelled_message="cancelled"):
    """Run a stage generator to its end: report each (fraction, message) it yields, ask `should_cancel` before
    every step (closing the generator releases what it holds), and return the generator's result."""
    while True:
        if should_cancel():
            steps.close()
            raise BakeCancelled(cancelled_message)
        try:
            fraction, message = next(steps)
        except StopIteration as stop:
            return stop.value
        if progress is not None:
            progress(fraction, message)


def finite_or_null(value):
    """`value` with every non-finite float replaced by None. JSON has no NaN or Infinity: Python writes them, but
    strict readers (jq, JavaScript) refuse the file. The one that occurs: PSNR of identical images (an all-black
    scene's bake and reference), written as null."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    return value


def write_json_atomic(path, data) -> Path:
    with atomic_output(path) as tmp:
        tmp.write_text(json.dumps(finite_or_null(data), indent=2, sort_keys=True, allow_nan=False) + "\n")
    return Path(path)


# The per-material SG count rule, measured by `python -m headless.bench --sections sgcount` (CNN at N = 2..16, R = 16,
# 60 s each, on spheres and room): N is the fewest SGs whose error in reflected radiance (training.sg_fit.glossy_error)
# stays within SG_COUNT_ERROR_BUDGET of the error with 16 on every scene. Below roughness 0.4 the GGX lobe is
# narrower than one R = 16 pixel, the measurement sees the light field's own noise rather than the fit, and such
# materials get the most SGs the settings allow.
SG_COUNT_CANDIDATES = (2, 4, 8, 12, 16)
SG_COUNT_ERROR_BUDGET = 0.15
SG_COUNT_BY_ROUGHNESS = ((0.4, None), (1.0, 8))  # (roughness below, SGs needed; None = the most allowed)


def auto_sg_count(roughness: float, most: int = 16) -> int:
    """SGs a glossy material of this roughness needs (the measured rule above), at most `most`."""
    most = most or 16
    need = next(n for bound, n in SG_COUNT_BY_ROUGHNESS if roughness < bound or bound >= 1.0)
    return most if need is None else min(need, most)
