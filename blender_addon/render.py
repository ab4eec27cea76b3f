"""Render stage: Cycles light-field and environment-visibility atlases with a custom OSL camera.

All rendering happens in a temporary scene that links the user's render-visible objects; the user's
scene, objects, lamps and world are never modified (lamps and the world are copied where the render
needs other settings). Each tile is one render call of many texels (shaders/lightfield_camera.osl).

Passes (directories in the bake directory, see bake_directory/lightfield_tiles.py):
  lightfield       emission, lamps and all indirect light arriving at each texel; the world is hidden
                   from the texel's own rays when the plan handles it with environment visibility
                   (IWEV), but still lights the scene indirectly.
  env_radiance     the unoccluded environment L_E over the whole sphere (one block, many samples)
  env_visibility   W_E per texel (shaders/env_visibility.py) from the texel's visibility V: a render against a
                   white world, every surface a holdout (black), lamps left out, primary rays only. Each pixel's
                   mean V times env_radiance's pixel is its L_E*V. Rendered against the world itself, a pixel's
                   few samples of the map's detail (an HDRI's small lamp) made L_E*V / L_E noisy, and W_E, clipped
                   to [0, 1], lost what the noise pushed over 1 (docs/design-additions.md section 55).
  env_occluded     those L_E*V images themselves (the diffuse irradiance from the sky needs them).
  midpoints        optional held-out light fields at midpoints between neighbouring texels, rendered with
                   MIDPOINT_SAMPLES_FACTOR times the samples: the interpolation metric then measures the
                   interpolation, not the noise of its own reference (a few hundred light fields: cheap).

Lamps enter the light field as light sources the texel's rays can hit: copies of the lamps are made
visible to camera rays (Cycles hides lamps from camera rays by default). A ray only finds a lamp that
covers a useful part of an octahedral pixel, so lamps smaller than LAMP_MIN_PIXEL_FRACTION of a pixel's
angular radius, seen from the median baked texel, are enlarged for the light field (same power; the
render says which and by how much). Sun lamps get at least the same angular size.
"""
from __future__ import annotations

import contextlib
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import bpy
import numpy as np
from mathutils import Vector

from ..bake_directory.bake_plan import BakeInputError, drive
from ..bake_directory.bake_report import save_png, update_report
from ..shaders.env_visibility import env_visibility
from ..bake_directory.exr_io import read_exr, write_exr
from ..bake_directory.image_metrics import LUMINANCE
from ..bake_directory.lightfield_tiles import (DEFAULT_TILE_MEGAPIXELS, TileIndex, blocks_to_images, images_to_blocks,
                                        parse_share, plan_tiles, preview_mosaic, read_preview_images,
                                        tile_is_finished, tile_samples, write_index)
from ..bake_directory.texel_maps import adjacent_texel_pairs, channels, read_texel_maps, texels_of_objects
from ..shaders.octahedral import downsample_octahedral
from .capture import scene_bvh
from .scene_analysis import active_scene, enable_nodes, quiet_stdout, remove_datablocks

CAMERA_SHADER = Path(__file__).resolve().parent.parent / "shaders" / "lightfield_camera.osl"
# env_occluded's L_E*V: the texel's visibility rendered against a white world, times env_radiance's pixel
ENV_VISIBILITY_ESTIMATOR = "visibility against a white world"
LAMP_MIN_PIXEL_FRACTION = 0.5  # of an octahedral pixel's angular radius (about 2/R radians)
ENV_RADIANCE_SAMPLES = 1024  # per pixel of the 64 x 64 map: 3.4 s on 2 CPU cores; 4096 fits the same SGs (§42)
ENV_RADIANCE_MIN_RESOLUTION = 64  # the environment SGs' fit wants finer than the light fields (training/env_fit.py)
MIDPOINT_SEED = 20200
MIDPOINT_SAMPLES_FACTOR = 16
PREVIEW_TEXELS = 16
TEMP_PREFIX = "SGLF render"
GPU_BACKEND = "OPTIX"  # the light-field camera is a custom OSL camera: Cycles runs those on the CPU and OptiX only


def optix_devices() -> list:
    """Cycles' OptiX device entries on this machine, from a refreshed device list."""
    preferences = bpy.context.preferences.addons["cycles"].preferences
    preferences.refresh_devices()
    return [entry for entry in preferences.get_devices_for_type(GPU_BACKEND) if entry.type == GPU_BACKEND]


@contextlib.contextmanager
def compute_device(scene, device: str):
    """Render `scene` with Cycles on the CPU, or for 'cuda' on every OptiX GPU Cycles finds. Setting the scene to
    "GPU Compute" alone renders on the CPU until a backend and its devices are enabled in Cycles' preferences: this
    enables them for the duration and restores the preferences and the scene's device afterwards. Yields the names
    of the devices used."""
    cycles = scene.cycles
    previous_device = cycles.device
    if device != "cuda":
        cycles.device = "CPU"
        try:
            yield ["CPU"]
        finally:
            cycles.device = previous_device
        return
    preferences = bpy.context.preferences.addons["cycles"].preferences
    gpus = optix_devices()
    if not gpus:
        raise BakeInputError("--device cuda: Cycles finds no OptiX GPU here (the light-field camera is an OSL camera, "
                             "which Cycles runs on the CPU and OptiX only); use --device cpu")
    previous_backend = preferences.compute_device_type
    previous_use = [(entry, entry.use) for entry in preferences.devices]
    preferences.compute_device_type = GPU_BACKEND
    for entry in preferences.devices:
        entry.use = entry.type == GPU_BACKEND
    cycles.device = "GPU"
    try:
        yield [entry.name for entry in gpus]
    finally:
        cycles.device = previous_device
        preferences.compute_device_type = previous_backend
        for entry, use in previous_use:
            entry.use = use


@dataclass
class RenderResult:
    seconds: float = 0.0
    tiles_rendered: dict = field(default_factory=dict)  # kind -> tiles rendered by this run
    tiles_skipped: dict = field(default_factory=dict)  # kind -> tiles already finished
    texels: int = 0
    rays_per_second: float = 0.0
    env_post_seconds: float = 0.0
    warnings: list = field(default_factory=list)
    devices: list = field(default_factory=list)  # what Cycles rendered on


def _noop_progress(fraction, message):
    pass


def _import_oslquery():
    try:
        import oslquery  # noqa: F401
    except ImportError:  # bpy as a module: the module ships inside the wheel, off sys.path
        scripts = bpy.utils.system_resource("SCRIPTS")
        bundled = os.path.join(os.path.dirname(scripts), "python", "lib",
                               f"python{sys.version_info.major}.{sys.version_info.minor}", "site-packages")
        if os.path.isdir(bundled) and bundled not in sys.path:
            sys.path.append(bundled)
        import oslquery  # noqa: F401


def render_still(scene, path) -> np.ndarray:
    """Render `scene` with its own settings into the EXR `path` (Cycles' log kept off stdout); (H, W, 3) float32."""
    scene.render.filepath = str(path)
    with active_scene(scene), quiet_stdout():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    if not Path(path).is_file():
        raise BakeInputError(f"the render of scene '{scene.name}' wrote no image ({path})")
    pixels, _, _ = read_exr(path, channels=["R", "G", "B"])
    return pixels


@contextlib.contextmanager
def _compiler_scratch():
    """Blender 5.0's cycles.osl compiles an internal script to a NamedTemporaryFile(delete=False) .oso that it never
    removes: one 15 KB file in the temp directory per bake. Compile inside a directory that is removed after."""
    previous = tempfile.tempdir
    with tempfile.TemporaryDirectory(prefix="sglf-oslc-") as scratch:
        tempfile.tempdir = scratch
        try:
            yield
        finally:
            tempfile.tempdir = previous


class _RenderScene:
    """A temporary scene that sees the user's render-visible objects through an atlas camera."""

    def __init__(self, scene, plan, work_dir: Path, texel_positions=None):
        self.source, self.plan, self.work_dir = scene, plan, work_dir
        self.texel_positions = np.zeros((1, 3)) if texel_positions is None else np.asarray(texel_positions)
        self.created = []  # (collection, datablock) to remove afterwards
        self.warnings = []
        self.devices = []
        self._contexts = contextlib.ExitStack()

    def __enter__(self):
        try:
            self._build()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def _build(self):
        source = self.source
        self.scene = self._new(bpy.data.scenes, f"{TEMP_PREFIX} {source.name}")
        self.lamps, self.others = [], []
        for obj in source.objects:
            if obj.hide_render or obj.type == "CAMERA":
                continue
            if obj.type == "LIGHT":
                self.lamps.append(self._visible_lamp(obj))
            else:
                self.others.append(obj)
        for obj in self.others + self.lamps:
            self.scene.collection.objects.link(obj)
        self.world = None
        if source.world is not None:
            self.world = source.world.copy()
            self.created.append((bpy.data.worlds, self.world))
        self.scene.world = self.world
        self.warnings += self._sanitise_environment_images()
        self._settings()
        self.devices = self._contexts.enter_context(compute_device(self.scene, self.plan.settings.device))
        self.camera = self._camera()
        self.holdout = self._new(bpy.data.materials, f"{TEMP_PREFIX} holdout")
        enable_nodes(self.holdout)
        nodes = self.holdout.node_tree.nodes
        for node in list(nodes):
            if node.type != "OUTPUT_MATERIAL":
                nodes.remove(node)
        hold = nodes.new("ShaderNodeHoldout")
        self.holdout.node_tree.links.new(hold.outputs[0], nodes["Material Output"].inputs["Surface"])
        self.white_world = self._new(bpy.data.worlds, f"{TEMP_PREFIX} white world")  # what V is rendered against
        enable_nodes(self.white_world)
        background = self.white_world.node_tree.nodes["Background"]
        background.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
        background.inputs["Strength"].default_value = 1.0

    def __exit__(self, *exc):
        self._contexts.close()
        remove_datablocks(self.created)
        self.created = []
        return False

    def _sanitise_environment_images(self) -> list[str]:
        """NaN, Inf or negative pixels in an environment image would poison every texel: render with a
        cleaned copy (the user's image stays as it is) and say so."""
        warnings = []
        if self.world is None or self.world.node_tree is None:
            return warnings
        for node in self.world.node_tree.nodes:
            image = getattr(node, "image", None) if node.type in ("TEX_ENVIRONMENT", "TEX_IMAGE") else None
            if image is None or image.size[0] == 0:
                continue
            pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
            image.pixels.foreach_get(pixels)
            bad = ~np.isfinite(pixels) | (pixels < 0)
            if not np.any(bad):
                continue
            clean = image.copy()
            self.created.append((bpy.data.images, clean))
            clean.pixels.foreach_set(np.where(bad, 0.0, pixels).astype(np.float32))
            clean.pack()  # the render reads the cleaned pixels, not the file on disk
            node.image = clean
            warnings.append(f"environment image '{image.name}': {int(bad.sum())} NaN/Inf/negative values "
                            "replaced by 0 for the bake")
        return warnings

    def _new(self, collection, name, *args):
        block = collection.new(name, *args)
        self.created.append((collection, block))
        return block

    def _visible_lamp(self, obj):
        data = obj.data.copy()
        self.created.append((bpy.data.lights, data))
        lamp = obj.copy()
        lamp.data = data
        self.created.append((bpy.data.objects, lamp))
        lamp.visible_camera = True
        angle = LAMP_MIN_PIXEL_FRACTION * 2.0 / self.plan.settings.lightfield_resolution  # radians
        location = np.array(obj.matrix_world.translation)
        distance = float(np.median(np.linalg.norm(self.texel_positions - location, axis=1)))
        if data.type in ("POINT", "SPOT"):
            wanted = distance * math.tan(angle)
            if data.shadow_soft_size < wanted:
                self.warnings.append(f"lamp '{obj.name}': radius {data.shadow_soft_size:.3g} m -> {wanted:.3g} m in "
                                     "the light field so its rays can hit it")
                data.shadow_soft_size = wanted
        elif data.type == "AREA":
            wanted = 2.0 * distance * math.tan(angle)
            if max(data.size, getattr(data, "size_y", 0.0)) < wanted:
                self.warnings.append(f"lamp '{obj.name}': size {data.size:.3g} m -> {wanted:.3g} m in the light field")
                data.size = max(data.size, wanted)
                if data.shape in ("RECTANGLE", "ELLIPSE"):
                    data.size_y = max(data.size_y, wanted)
        elif data.type == "SUN" and data.angle < 2 * angle:
            self.warnings.append(f"sun '{obj.name}': angle {math.degrees(data.angle):.2g} deg -> "
                                 f"{math.degrees(2 * angle):.2g} deg in the light field")
            data.angle = 2 * angle
        return lamp

    def _settings(self):
        scene, source = self.scene, self.source
        scene.render.engine = "CYCLES"
        cycles, user = scene.cycles, source.cycles
        for name in ("max_bounces", "diffuse_bounces", "glossy_bounces", "transmission_bounces",
                     "volume_bounces", "transparent_max_bounces", "caustics_reflective", "caustics_refractive",
                     "blur_glossy", "sample_clamp_direct", "sample_clamp_indirect"):
            setattr(cycles, name, getattr(user, name))
        if min(user.max_bounces, user.diffuse_bounces) == 0:
            self.warnings.append(f"the scene allows {min(user.max_bounces, user.diffuse_bounces)} diffuse bounces: "
                                 "baked surfaces still reflect the light of the surfaces they see (one bounce more)")
        cycles.use_denoising = False
        cycles.use_adaptive_sampling = False
        cycles.pixel_filter_type = "BOX"
        cycles.filter_width = 1.0
        cycles.seed = 0
        scene.render.film_transparent = False
        scene.render.resolution_percentage = 100
        scene.render.use_persistent_data = True  # the scene's BVH survives from one tile to the next
        scene.render.image_settings.file_format = "OPEN_EXR"
        scene.render.image_settings.color_depth = "32"
        scene.render.image_settings.color_mode = "RGB"
        scene.render.use_compositing = False
        scene.render.use_sequencer = False

    def _camera(self):
        _import_oslquery()
        import cycles.osl

        text = self._new(bpy.data.texts, f"{TEMP_PREFIX} camera.osl")
        text.write(CAMERA_SHADER.read_text())
        data = self._new(bpy.data.cameras, f"{TEMP_PREFIX} camera")
        data.type = "CUSTOM"
        data.custom_mode = "INTERNAL"
        data.custom_shader = text
        data.clip_start, data.clip_end = 1e-6, 1e9
        messages = []
        with _compiler_scratch():
            ok = cycles.osl.update_custom_camera_shader(data, lambda kind, message: messages.append(message))
        if not ok:
            raise BakeInputError("the light-field camera shader did not compile: " + "; ".join(messages))
        camera = self._new(bpy.data.objects, f"{TEMP_PREFIX} camera", data)
        self.scene.collection.objects.link(camera)
        self.scene.camera = camera
        return camera

    def configure(self, kind: str, samples: int | None = None, bounce_left_out: str = "diffuse"):
        """Scene state for one pass: which objects, world visibility, material override, samples (`samples`, else
        the pass's), and bounces: the scene's less one in all and one of `bounce_left_out` (diffuse or glossy),
        the scattering the baked surface adds to every path through the light field."""
        scene, settings = self.scene, self.plan.settings
        environment_pass = kind in ("env_radiance", "env_occluded")
        linked = set(scene.collection.objects)
        wanted = set() if kind == "env_radiance" else set(self.others)
        if kind in ("lightfield", "midpoints"):
            wanted |= set(self.lamps)
        wanted.add(self.camera)
        for obj in linked - wanted:
            scene.collection.objects.unlink(obj)
        for obj in wanted - linked:
            scene.collection.objects.link(obj)
        scene.view_layers[0].material_override = self.holdout if environment_pass else None
        scene.world = self.white_world if kind == "env_occluded" else self.world
        if self.world is not None:
            self.world.cycles_visibility.camera = environment_pass or not self.plan.environment.iwev
        user, cycles = self.source.cycles, scene.cycles
        if environment_pass:
            cycles.max_bounces = 0
        else:
            cycles.max_bounces = max(user.max_bounces - 1, 0)
            cycles.diffuse_bounces = max(user.diffuse_bounces - (bounce_left_out == "diffuse"), 0)
            cycles.glossy_bounces = max(user.glossy_bounces - (bounce_left_out == "glossy"), 0)
        scene.cycles.samples = (ENV_RADIANCE_SAMPLES if kind == "env_radiance"
                                else samples or pass_samples(kind, settings.samples))

    def render(self, positions, normals, offsets, flags, columns, rows, resolution, name) -> np.ndarray:
        """Render `columns` x `rows` blocks; inputs are (count, 3) arrays; returns (H, W, 3) float32."""
        count = len(positions)
        textures = {}
        for key, values in (("position", positions), ("normal", normals),
                            ("offset", np.stack([offsets, flags, np.zeros(count)], axis=-1))):
            grid = np.zeros((rows * columns, 3), np.float32)
            grid[:count] = values
            path = self.work_dir / f"{name}_{key}.exr"
            write_exr(path, grid.reshape(rows, columns, 3), precision="float", channels=["R", "G", "B"])
            textures[key] = str(path)
        props = self.camera.data.cycles_custom
        props["texel_position"], props["texel_normal"] = textures["position"], textures["normal"]
        props["texel_offset"] = textures["offset"]
        props["columns"], props["rows"], props["resolution"] = columns, rows, resolution
        self.camera.data.update_tag()
        self.scene.render.resolution_x, self.scene.render.resolution_y = columns * resolution, rows * resolution
        output = self.work_dir / f"{name}_render.exr"
        pixels = render_still(self.scene, output)
        for key in textures.values():
            Path(key).unlink(missing_ok=True)
        output.unlink(missing_ok=True)
        return pixels


def pass_samples(kind: str, samples: int) -> int:
    """Samples per pixel of a pass: the plan's, and MIDPOINT_SAMPLES_FACTOR times that for held-out midpoints."""
    return min(samples * MIDPOINT_SAMPLES_FACTOR, 65536) if kind == "midpoints" else samples


def valid_texels(atlas: np.ndarray) -> np.ndarray:
    """(T, 2) atlas [row, col] of the texels to render, row-major."""
    rows, cols = np.nonzero(channels(atlas, "valid") > 0)
    return np.stack([rows, cols], axis=-1)


def _texel_inputs(atlas, texels):
    r, c = texels[:, 0], texels[:, 1]
    return (channels(atlas, "P.X", 3)[r, c].astype(np.float64), channels(atlas, "Ng.X", 3)[r, c].astype(np.float64),
            channels(atlas, "ray_offset")[r, c].astype(np.float64))


def _camera_inputs(atlas, texels) -> np.ndarray:
    """(T, 7) what the OSL camera renders each texel from: its surface point, normal and ray offset. Tile hashes
    cover them, so a tile rendered for another capture's texels (another layout, a moved object) is rendered again
    instead of being taken as finished."""
    positions, normals, offsets = _texel_inputs(atlas, texels)
    return np.column_stack([positions, normals, offsets])


def midpoint_pairs(atlas: np.ndarray, count: int, seed: int = MIDPOINT_SEED, texel_info=None,
                   objects=None) -> np.ndarray:
    """(M, 4) [row, col, row2, col2]: `count` random adjacent valid texels of one object (adjacent_texel_pairs),
    of the named `objects` (all when None; texel_info from read_texel_maps names them)."""
    pairs = adjacent_texel_pairs(atlas)
    if objects is not None:
        pairs = pairs[texels_of_objects(atlas, texel_info, pairs[:, :2], objects)]
    pick = np.random.default_rng(seed).choice(len(pairs), size=min(count, len(pairs)), replace=False)
    return pairs[np.sort(pick)]


def _midpoint_inputs(scene, atlas, pairs):
    """Camera inputs of the held-out midpoints: the surface point halfway between two adjacent texels, their blended
    normal and the larger ray offset. The chord midpoint of two texels on a curved surface lies inside it (1.5 cm
    on the demo spheres at Draft, 70 times the ray offset: every ray started inside the sphere and the midpoints
    rendered black), so it is moved onto the surface by a ray cast along the blended normal."""
    p1, n1, o1 = _texel_inputs(atlas, pairs[:, :2])
    p2, n2, o2 = _texel_inputs(atlas, pairs[:, 2:])
    normal = n1 + n2
    normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-12)
    position = 0.5 * (p1 + p2)
    reach = np.linalg.norm(p1 - p2, axis=1)  # far above the sagitta of any surface the two texels lie on
    with active_scene(scene):
        bvh, _ = scene_bvh(scene, bpy.context.evaluated_depsgraph_get())
    for i in range(len(position)) if bvh is not None else ():
        hit, _, _, _ = bvh.ray_cast(Vector(position[i] + reach[i] * normal[i]), Vector(-normal[i]), 2.0 * reach[i])
        if hit is not None:
            position[i] = hit
    return position, normal, np.maximum(o1, o2)


def _mono(images):
    return (images @ LUMINANCE)[..., None]


def plan_lightfield_tiles(atlas, texel_info, texels, plan, resolution, max_megapixels):
    """The texels in render order and the light-field tiles, in groups that differ in samples or in the bounce the
    light field leaves out: the texels of objects with SGs (with those of lightmap-only objects where their samples
    are the same), those of metal-only objects (`metal_0000.exr`, ...: a glossy bounce left out), then those of
    lightmap-only objects with samples of their own (`lightmap_0000.exr`, ...)."""
    settings = plan.settings
    with_sgs = texels_of_objects(atlas, texel_info, texels, plan.sg_objects)
    metal = texels_of_objects(atlas, texel_info, texels, plan.glossy_bounce_objects)
    own_samples = settings.lightmap_pass_samples != settings.samples
    groups = [("tile", ~metal & (with_sgs if own_samples else True), 0, "diffuse"),
              ("metal", metal, 0, "glossy"),
              ("lightmap", ~with_sgs & own_samples, settings.lightmap_pass_samples, "diffuse")]
    return _grouped_tiles([(prefix, texels[mask], _camera_inputs(atlas, texels[mask]), samples, bounce)
                           for prefix, mask, samples, bounce in groups], texels, resolution, max_megapixels)


def _grouped_tiles(groups, ids, resolution, max_megapixels):
    """Tiles of (prefix, ids, camera inputs, samples, bounce left out) groups, numbered on from one group to the
    next; returns the ids in tile order (`ids` when every group is empty) and the tiles."""
    ordered, tiles = [], []
    for prefix, group_ids, inputs, samples, bounce in groups:
        if not len(group_ids):
            continue
        group = plan_tiles(group_ids, resolution, max_megapixels=max_megapixels, prefix=prefix, inputs=inputs)
        for tile in group:
            tile.index += len(tiles)
            tile.samples, tile.bounce_left_out = samples, bounce
        ordered.append(group_ids)
        tiles += group
    return (np.concatenate(ordered) if ordered else ids), tiles


def render_stage(scene, plan, out_dir, *, progress=_noop_progress, should_cancel=lambda: False,
                 **options) -> RenderResult:
    """Render every pass the plan needs into `out_dir`; finished tiles are kept and skipped."""
    return drive(render_steps(scene, plan, out_dir, **options), progress, should_cancel, "render cancelled")


def render_steps(scene, plan, out_dir, *, share: str | None = None, midpoints: int = 0,
                 max_tile_megapixels: float = DEFAULT_TILE_MEGAPIXELS):
    """The render stage as a generator: yields (fraction, message) after every tile, returns RenderResult.
    Closing it early (cancel) removes the temporary render scene; finished tiles stay on disk."""
    start = time.perf_counter()
    out_dir = Path(out_dir)
    plan_hash = plan.stage_hash("render")
    atlas, texel_info = read_texel_maps(out_dir, plan.stage_hash("capture"))
    settings = plan.settings
    resolution = settings.lightfield_resolution
    result = RenderResult()
    texels = valid_texels(atlas)
    if plan.settings.irradiance_detail > 1:  # the capture's detail image holds every surface's diffuse light: the
        texels = texels[texels_of_objects(atlas, texel_info, texels, plan.sg_objects)]  # lightmap-only need none
    texels, lightfield_plan = plan_lightfield_tiles(atlas, texel_info, texels, plan, resolution, max_tile_megapixels)
    result.texels = len(texels)
    jobs = [("lightfield", texels, _texel_inputs(atlas, texels), 3)] if len(texels) else []
    planned = {"lightfield": lightfield_plan}  # tiles grouped by samples and bounce; the other passes split evenly
    if midpoints > 0 and plan.sg_objects:
        pairs = midpoint_pairs(atlas, midpoints, texel_info=texel_info, objects=plan.sg_objects)  # what training reads
        metal = texels_of_objects(atlas, texel_info, pairs[:, :2], plan.glossy_bounce_objects)
        order = np.argsort(metal, kind="stable")  # the dielectrics' pairs, then the metals': the tiles' order
        pairs, metal = pairs[order], metal[order]
        inputs = _midpoint_inputs(scene, atlas, pairs)
        groups = [(prefix, pairs[mask], np.concatenate([a[mask] for a in inputs[:2]], axis=1), 0, bounce)
                  for prefix, mask, bounce in (("tile", ~metal, "diffuse"), ("metal", metal, "glossy"))]
        planned["midpoints"] = _grouped_tiles(groups, pairs, resolution, max_tile_megapixels)[1]
        jobs.append(("midpoints", pairs, inputs, 3))
    iwev_channels = plan.environment.iwev_channels if plan.environment.iwev else 0
    if iwev_channels and len(texels):
        jobs.append(("env_visibility", texels, _texel_inputs(atlas, texels), iwev_channels))
    work = []  # (kind, kind_dir, index, tile, inputs)
    for kind, ids, inputs, channel_count in jobs:
        kind_dir = out_dir / kind
        tiles = planned[kind] if kind in planned else plan_tiles(
            ids, resolution, max_megapixels=max_tile_megapixels, inputs=_camera_inputs(atlas, ids))
        index = TileIndex(kind, plan_hash, resolution, pass_samples(kind, settings.samples), channel_count, tiles)
        write_index(kind_dir, index)
        mine = parse_share(share, len(tiles))
        done = [t for t in tiles if t.index in mine and tile_is_finished(kind_dir, index, t)]
        if kind == "env_visibility":  # its L_E*V images are kept too: diffuse needs the sky's irradiance
            occluded_index = TileIndex("env_occluded", plan_hash, resolution, settings.samples, 3, tiles)
            write_index(out_dir / "env_occluded", occluded_index)
            done = [t for t in done if tile_is_finished(out_dir / "env_occluded", occluded_index, t,
                                                        made_by={"visibility": ENV_VISIBILITY_ESTIMATOR})]
        result.tiles_skipped[kind] = len(done)
        result.tiles_rendered[kind] = 0
        offset = 0
        for tile in tiles:
            count = len(tile.texels)
            if tile.index in mine and tile not in done:
                work.append((kind, kind_dir, index, tile, tuple(a[offset:offset + count] for a in inputs)))
            offset += count
    total_work = sum(len(t.texels) * tile_samples(index, t) for _, _, index, t, _ in work) or 1  # pixel samples
    finished_work, render_seconds, rays = 0, 0.0, 0
    if not jobs:
        yield 1.0, "no light fields to render: every baked surface is an irradiance lightmap, whose light the " \
                   "capture's detail image holds"
    elif not work:
        yield 1.0, "all tiles already rendered"
    else:
        yield 0.0, f"{len(work)} tile{'s' if len(work) != 1 else ''} to render"  # starts the stage's clock (ETA)
        with tempfile.TemporaryDirectory(prefix=".sglf-render-", dir=out_dir) as tmp, \
                _RenderScene(scene, plan, Path(tmp), _texel_inputs(atlas, texels)[0]) as renderer:
            result.warnings.extend(renderer.warnings)
            result.devices = renderer.devices
            if settings.device == "cuda":  # measured: minutes on a fresh H100, seconds once cached
                yield 0.0, f"rendering on {', '.join(renderer.devices)} (OptiX; the first render on a machine " \
                           "compiles its kernels)"
            env_radiance = None
            for kind, kind_dir, index, tile, (positions, normals, offsets) in work:
                flags = np.ones(len(positions))
                samples = tile_samples(index, tile)
                tick = time.perf_counter()
                if kind == "env_visibility":
                    if env_radiance is None:
                        fine_env_radiance, env_radiance = _render_env_radiance(renderer, resolution)
                        write_exr(out_dir / "env_radiance.exr", fine_env_radiance, precision="float",
                                  metadata={"plan_hash": plan_hash})
                    renderer.configure("env_occluded")
                    pixels = renderer.render(positions, normals, offsets, flags, tile.columns, tile.rows,
                                             resolution, f"{kind}_{tile.index}")
                    render_seconds += time.perf_counter() - tick
                    post = time.perf_counter()
                    visible = np.clip(np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0).mean(axis=-1), 0.0, 1.0)
                    visible = blocks_to_images(visible[..., None], tile.columns, tile.rows, resolution,
                                               len(positions))
                    occluded = (visible * env_radiance[None]).astype(np.float32)  # L_E*V
                    write_exr(out_dir / "env_occluded" / tile.file,
                              images_to_blocks(occluded, tile.columns, tile.rows), precision="half",
                              channels=["R", "G", "B"],
                              metadata={"plan_hash": plan_hash, "tile_hash": tile.hash, "resolution": resolution,
                                        "samples": index.samples, "kind": "env_occluded",
                                        "visibility": ENV_VISIBILITY_ESTIMATOR})
                    radiance = env_radiance
                    if index.channels == 1:
                        occluded, radiance = _mono(occluded), _mono(env_radiance)
                    count = len(positions)
                    w = env_visibility(occluded.reshape(count, -1, index.channels),
                                       radiance.reshape(-1, index.channels), normals,
                                       _roughness(atlas, tile.texels), resolution)
                    pixels = images_to_blocks(w.reshape(count, resolution, resolution, index.channels),
                                              tile.columns, tile.rows)
                    result.env_post_seconds += time.perf_counter() - post
                else:
                    renderer.configure(kind, samples, tile.bounce_left_out)
                    pixels = renderer.render(positions, normals, offsets, flags, tile.columns, tile.rows,
                                             resolution, f"{kind}_{tile.index}")
                    seconds = time.perf_counter() - tick
                    render_seconds += seconds
                    rays += len(positions) * resolution * resolution * samples // 2
                if not np.all(np.isfinite(pixels)):
                    result.warnings.append(f"{kind} {tile.file}: non-finite pixels set to 0")
                    pixels = np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0)
                write_exr(kind_dir / tile.file, pixels, precision="half",
                          channels=["R", "G", "B"][:index.channels] if index.channels == 3 else ["Y"],
                          metadata={"plan_hash": plan_hash, "tile_hash": tile.hash, "resolution": resolution,
                                    "samples": samples, "kind": kind})
                result.tiles_rendered[kind] += 1
                finished_work += len(tile.texels) * samples
                yield finished_work / total_work, f"{kind} {tile.file} done ({len(tile.texels)} texels)"
    pictures = _save_previews(out_dir, plan_hash, [kind for kind, *_ in jobs])
    result.seconds = time.perf_counter() - start
    result.rays_per_second = rays / render_seconds if render_seconds > 0 else 0.0
    update_report(out_dir, plan.stage_hash("capture"), timings_s={"render": result.seconds},
                  render={"tiles_rendered": result.tiles_rendered, "tiles_skipped": result.tiles_skipped,
                          "rays_per_second": round(result.rays_per_second),
                          "env_post_seconds": round(result.env_post_seconds, 3), "share": share or "all",
                          "devices": result.devices, "pictures": pictures})
    return result


def _save_previews(out_dir, plan_hash, kinds) -> list[str]:
    """A mosaic of 16 texels' images per pass, once every tile of it exists (not on a partial farm share)."""
    names = []
    for kind in kinds:
        try:
            images = read_preview_images(out_dir / kind, plan_hash, PREVIEW_TEXELS)
        except BakeInputError:
            continue
        name = f"render_{kind}.png"
        save_png(out_dir / name, preview_mosaic(images))
        names.append(name)
    return names


def _roughness(atlas, texels):
    t = np.asarray(texels, np.int64)
    return channels(atlas, "roughness")[t[:, 0], t[:, 1]].astype(np.float64)


def env_radiance_resolution(resolution: int) -> int:
    """The environment map's resolution: a multiple of the light fields' (it averages down to theirs exactly), at
    least ENV_RADIANCE_MIN_RESOLUTION."""
    return resolution * max(1, -(-ENV_RADIANCE_MIN_RESOLUTION // resolution))


def _render_env_radiance(renderer, resolution):
    """The unoccluded environment over the whole sphere, one block at env_radiance_resolution, ENV_RADIANCE_SAMPLES
    samples: the fine map (for the environment SGs) and the map averaged down to `resolution` (for W_E)."""
    renderer.configure("env_radiance")
    fine = env_radiance_resolution(resolution)
    pixels = renderer.render(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]), np.zeros(1), np.full(1, 2.0),
                             1, 1, fine, "env_radiance")
    pixels = np.maximum(np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0), 0.0)
    return pixels, downsample_octahedral(pixels, resolution)
