"""Scene analysis: decide what the bake models (DESIGN section 6) and build the BakePlan.

Reads the scene only: it is evaluated as a render evaluates it (render_evaluation), every setting put back after.
"""
from __future__ import annotations

import contextlib
import os
import sys
from dataclasses import dataclass, field

import bpy
import numpy as np

from ..bake_directory.image_metrics import LUMINANCE
from ..bake_directory.bake_plan import (ALPHA_NOTE, BACK_FACES_NOTE, COAT_NOTE, GLOSSY_ROUGHNESS_MAX,
                                        RENDERER_LIT_NOTE, ROUGH_METALLIC_MAX, BakeInputError, BakePlan, BakeSettings,
                                        EnvironmentPlan, MaterialPlan, ObjectPlan, auto_sg_count)
from .lightmap_modifier import MODIFIER_TYPES, user_modifiers
from .stand_ins import (COPYABLE, INSTANCE_COPY_KEY, STAND_IN_TYPES, copied, copied_state, copies_of, is_copy,
                        is_stand_in, modifiers_turned_off, stand_in_of)
from .temporary_settings import temporarily
from .surface_shaders import COPY_KEY, LeafInputs, NeedsNodes, analyse_surface, input_constant, leaves

# An environment whose luminance-weighted chroma (max-min)/max stays below this is treated as grey:
# one IWEV channel instead of three.
ACHROMATIC_CHROMA_MAX = 0.05


def uses_nodes(id_block) -> bool:
    """Blender 5 always shades with the node tree (use_nodes is deprecated); older versions may not."""
    if id_block is None or id_block.node_tree is None:
        return False
    return bpy.app.version >= (5, 0, 0) or id_block.use_nodes


# Cycles' custom OSL camera, which renders the light-field atlas, first shipped in Blender 4.5.
MIN_BLENDER = (4, 5, 0)


def require_blender_version(version=None) -> None:
    """One clear error where this Blender is too old for the bake (bpy as a module or a script; the extension's
    manifest keeps older Blenders from installing it)."""
    version = tuple(version or bpy.app.version)
    if version < MIN_BLENDER:
        raise BakeInputError(
            f"the bake needs Blender {'.'.join(map(str, MIN_BLENDER))} or later: its light-field render uses Cycles' "
            f"custom OSL camera, which Blender {'.'.join(map(str, version))} does not have")


def enable_nodes(id_block) -> None:
    if bpy.app.version < (5, 0, 0):
        id_block.use_nodes = True


def remove_datablocks(created) -> None:
    """Remove (collection, datablock) pairs, last made first; ones already gone are skipped."""
    for collection, block in reversed(created):
        try:
            collection.remove(block)
        except (ReferenceError, RuntimeError):
            pass


def empty_node_material(name: str):
    """A new material whose node tree holds only its Material Output (to be wired by the caller)."""
    material = bpy.data.materials.new(name)
    enable_nodes(material)
    for node in list(material.node_tree.nodes):
        if node.type != "OUTPUT_MATERIAL":
            material.node_tree.nodes.remove(node)
    return material


def _input_value(node, name, default):
    value, linked = input_constant(node, name, default)
    return (default if value is None else value), linked


BAKED_COPY_KEY = COPY_KEY  # set by the apply stage on its copies; the plan looks through them


def unbaked(material):
    """The user's material behind an SG-baked copy (the plan of a baked scene equals the plan before)."""
    if material is not None and BAKED_COPY_KEY in material:
        return bpy.data.materials.get(material[BAKED_COPY_KEY], material)
    return material


def analyse_material(material, settings: BakeSettings, surface=None) -> MaterialPlan:
    """The plan of one material from its surface (surface_shaders.analyse_surface): baked BSDFs get SGs (glossy),
    an irradiance lightmap (rough dielectrics, Diffuse BSDFs) or nothing; a surface with anything the bake does not
    model is left to the renderer with the reason. A textured roughness makes the material glossy here; its SGs per
    texel follow the roughness the capture stage measures over the lightmap (capture.measure_surfaces). `surface`:
    the material's analyse_surface when the caller has it already."""
    material = unbaked(material)
    name = material.name if material else "(no material)"
    if material is None:
        return MaterialPlan(name, 1.0, 0.0, False, 0, "no material: Blender renders it diffuse grey")
    surface = analyse_surface(material) if surface is None else surface
    if surface.renderer_reasons:
        return MaterialPlan(name, 1.0, 0.0, False, 0,
                            "left to the renderer: " + "; ".join(surface.renderer_reasons))
    if not surface.leaves:
        return MaterialPlan(name, 1.0, 0.0, False, 0,
                            "emission only: not baked, its emission is the light it shows" if surface.emissive
                            else "only a Transparent BSDF: not baked, it shows what is behind" if surface.transparent
                            else "no BSDF in its surface (holdout): not baked")
    most = settings.sg_count or 16
    specular = [leaf for leaf in surface.leaves if leaf.specular]
    textured = sorted({n for leaf in surface.leaves for n in leaf.linked})
    note = f"; textured inputs ({', '.join(textured)}) read per pixel" if textured else ""
    if any(leaf.coat for leaf in surface.leaves):
        note += "; " + COAT_NOTE
    if surface.see_through:
        note += "; " + ALPHA_NOTE
    elif surface.two_sided:
        note += "; " + BACK_FACES_NOTE
    if surface.renderer_lit:
        note += "; " + ", ".join(surface.renderer_lit) + " " + RENDERER_LIT_NOTE
    if any(leaf.roughness is None for leaf in specular):
        metallic = min((0.5 if leaf.metallic is None else leaf.metallic) for leaf in surface.leaves)
        return MaterialPlan(name, 0.0, metallic, True, most,
                            f"roughness is textured: glossy, up to {most} SGs per texel as the roughness measured over "
                            "its lightmap needs" + note, textured=textured)
    roughness = min((leaf.roughness for leaf in specular), default=1.0)
    # The material is as metallic as its least metallic BSDF (a Diffuse beside a Glossy is not a metal); a textured
    # metallic counts as half.
    metallic = min((0.5 if leaf.metallic is None else leaf.metallic for leaf in surface.leaves), default=0.0)
    rough_metal = roughness >= GLOSSY_ROUGHNESS_MAX and metallic >= ROUGH_METALLIC_MAX
    glossy = bool(specular) and (roughness < GLOSSY_ROUGHNESS_MAX or rough_metal)
    count = 0 if not glossy else most if settings.uniform_sg_count else auto_sg_count(roughness, most)
    irradiance_only = False
    kinds = sorted({leaf.node_type for leaf in surface.leaves} - {"BSDF_PRINCIPLED"})
    what = f"roughness {roughness:.2f}" if specular else "diffuse BSDF"
    if rough_metal:
        reason = (f"roughness {roughness:.2f} >= {GLOSSY_ROUGHNESS_MAX} but metallic {metallic:.2f}: "
                  "all its light is specular, so light-field SGs")
    elif glossy:
        reason = f"roughness {roughness:.2f} < {GLOSSY_ROUGHNESS_MAX}: glossy, needs light-field SGs"
    elif surface.emissive:
        reason = f"{what}, emissive: not baked, its emission is the light it shows"
    elif settings.rough_materials == "irradiance":
        irradiance_only = True
        reason = (f"{what}: irradiance lightmap, no SGs (its lobe is wider than ~40 deg; the specular is the "
                  "split-sum estimate of the irradiance's)" if specular else f"{what}: irradiance lightmap, no SGs")
    else:
        reason = (f"{what}: not baked (rough materials: renderer), the renderer's own lighting; in EEVEE only its "
                  "irradiance volumes give it indirect light")
    if glossy and count < most:
        reason += f"; {count} SGs are within the error budget at this roughness"
    if kinds:
        reason += "; " + ", ".join(k.replace("BSDF_", "").lower() for k in kinds) + " BSDF"
    return MaterialPlan(name, float(roughness), float(metallic), glossy, count, reason + note, irradiance_only,
                        textured=textured)


def principled_surface(material) -> dict:
    """Base colour, roughness, metallic and normal-incidence Fresnel F0 of a material's first baked BSDF where they
    are constants, as Blender 4+ defines them: F0 = mix(((ior-1)/(ior+1))^2 * 2 * specular_level * tint, base,
    metallic). A linked input reads as Blender's default for it (base 0.8 grey, roughness 0.5, metallic 0) and
    'textured' lists the linked inputs: the capture stage measures those per texel. Materials without a baked BSDF
    render as Blender's default grey diffuse."""
    found = leaves(unbaked(material))
    if not found:
        return {"base_color": [0.8, 0.8, 0.8], "roughness": 1.0, "metallic": 0.0, "f0": [0.04, 0.04, 0.04],
                "textured": []}
    node = found[0][1]
    values = LeafInputs(None, node)

    def constant(quantity, default):
        try:
            value = quantity()
        except NeedsNodes:
            return default
        return default if hasattr(value, "is_linked") else value

    base = np.clip(np.asarray(constant(values.base_colour, (0.8, 0.8, 0.8))[:3], float), 0.0, 1.0)
    roughness = float(np.clip(constant(values.roughness, 0.5), 0.0, 1.0))
    metallic = float(np.clip(constant(values.metallic, 0.0), 0.0, 1.0))
    f0 = constant(values.f0, None)
    if f0 is None:
        f0 = (1 - metallic) * np.full(3, 0.04) + metallic * base
    textured = sorted(s.name for s in node.inputs if s.type != "SHADER" and s.enabled and s.is_linked)
    return {"base_color": [float(c) for c in base], "roughness": roughness, "metallic": metallic,
            "f0": [float(c) for c in np.clip(np.asarray(f0, float), 0.0, 1.0)], "textured": textured}


NESTED_ID = 2147483647  # an unused level of an instance's persistent_id


@dataclass
class Instanced:
    """What one object instances (geometry nodes, a collection, particles, vertex or face instancing), in the
    depsgraph's order: each entry (source object name, world matrix as nested lists)."""
    how: str
    count: int = 0
    sources: set = field(default_factory=set)  # the instanced objects' names; "generated geometry" for node output
    entries: list = field(default_factory=list)
    nested: bool = False  # instances inside instances (a collection through Collection Info, nested instancers)
    copies: bool = False  # baked as object copies (stand_ins.copy_instances): the settings ask for it, or done
    # Geometry made inside the node tree (its entry's source is the instancer itself): entry index -> (vertex
    # coordinates, triangles, material names) of its mesh; `meshes`: entry index -> a copy of that mesh (capture).
    generated: dict = field(default_factory=dict)
    meshes: dict = field(default_factory=dict)
    not_mesh: bool = False  # node-made geometry that is not a mesh (curves, points): nothing to copy

    def description(self) -> str:
        return f"{self.count} {self.how} instance{'s' if self.count != 1 else ''} of {', '.join(sorted(self.sources))}"

    @property
    def copyable(self) -> bool:
        """Whether these instances bake only as object copies (stand_ins.copy_instances): they carry no attribute of
        their own, or there is no object to switch materials on."""
        return not self.not_mesh and (self.how in COPYABLE or self.nested or "generated geometry" in self.sources)

    def unsupported(self) -> str:
        """Why per-instance lightmaps cannot be built for these instances ("" when they can)."""
        if self.copyable and self.copies:
            return ""
        hint = "; Instances as Copies bakes each as an object copy" if self.copyable else ""
        if "generated geometry" in self.sources:
            return "their geometry is made inside the node tree, not an object whose materials the bake can switch" \
                + (hint or "; it is not a mesh, so no copy can stand in for it")
        if self.how in COPYABLE:
            return (f"{self.how} instances carry no attribute of their own for the baked material to find its "
                    f"texels by{hint}")
        if self.nested:
            return "instances nested inside instances share one attribute, not one lightmap tile each" + hint
        return ""

    def reason(self) -> str:
        why = self.unsupported()
        if why:
            return f"left to the renderer: {self.description()} ({why}; each keeps the renderer's own lighting)"
        if self.copies:
            return (f"its {self.description()}: each baked as an object copy with texels of its own, which renders "
                    "in its place until Remove SG Bake (listed below)")
        return f"its {self.description()}: each baked with texels of its own (listed below)"


def instances_by_instancer(depsgraph, keep_meshes=()) -> dict:
    """Instancer name -> Instanced, from the evaluated scene's instances. For the instancers named in `keep_meshes`,
    each instance of node-made geometry gets a copy of its mesh (Instanced.meshes), which the caller owns."""
    found, surfaces = {}, {}
    for instance in depsgraph.object_instances:
        if not instance.is_instance or instance.parent is None:
            continue
        parent = instance.parent.original
        if instance.object.original == parent and parent.type != "MESH":
            continue  # a text's, curve's or metaball's own surface, which Blender hands over as an instance
        if instance.object.type == "EMPTY":
            continue  # an empty renders nothing; what it instances in turn comes as instances of its own
        if parent.name not in found:
            if parent.type == "EMPTY" and parent.instance_type == "COLLECTION":
                how = "collection"
            elif parent.type == "MESH" and parent.instance_type in ("VERTS", "FACES"):
                how = "vertex" if parent.instance_type == "VERTS" else "face"
            elif getattr(parent, "particle_systems", None) and len(parent.particle_systems):
                how = "particle"
            else:
                how = "geometry nodes"
            found[parent.name] = Instanced(how)
        entry = found[parent.name]
        entry.count += 1
        source = instance.object.original
        entry.sources.add(source.name if source != parent else "generated geometry")
        entry.entries.append((source.name, [list(row) for row in instance.matrix_world]))
        levels = [i for i in instance.persistent_id if i != NESTED_ID]
        entry.nested |= len(levels) > (1 if how == "collection" else 2)
        if source == parent:  # node-made geometry: read now, its object lives only during this iteration
            data = instance.object.data
            if not isinstance(data, bpy.types.Mesh):
                entry.not_mesh = True
                continue
            if data.as_pointer() not in surfaces:  # instances of one node-made mesh share it
                _, verts, _, coords = loop_triangle_arrays(data)
                surfaces[data.as_pointer()] = (coords, verts, tuple(m.name if m else "" for m in data.materials))
            entry.generated[len(entry.entries) - 1] = surfaces[data.as_pointer()]
            if parent.name in keep_meshes:
                entry.meshes[len(entry.entries) - 1] = bpy.data.meshes.new_from_object(instance.object)
    return found


def copied_instancers(scene) -> dict:
    """Instancer name -> Instanced, for the instancers whose instances the bake replaced by object copies (they no
    longer instance): rebuilt from the copies, in the instancer's order."""
    found = {}
    for instancer in scene.objects:
        if copied(instancer):
            state = copied_state(instancer)
            entry = Instanced(state["how"], nested=state["nested"], copies=True)
            for copy in copies_of(instancer):
                source = copy[INSTANCE_COPY_KEY]["source"]
                entry.count += 1
                entry.entries.append((source, [list(row) for row in copy.matrix_world]))
                if copy[INSTANCE_COPY_KEY].get("generated"):  # node-made geometry: the copy holds its mesh
                    entry.sources.add("generated geometry")
                    _, verts, _, coords = loop_triangle_arrays(copy.data)
                    entry.generated[len(entry.entries) - 1] = (coords, verts, tuple(
                        m.name if m else "" for m in copy.data.materials))
                else:
                    entry.sources.add(source)
            found[instancer.name] = entry
    return found


def scene_instancers(scene, depsgraph, settings) -> dict:
    """Every instancer of the scene (instances_by_instancer), those replaced by copies included, each marked with
    whether its instances are (to be) baked as copies."""
    found = {**instances_by_instancer(depsgraph), **copied_instancers(scene)}
    for instanced in found.values():
        instanced.copies |= settings.instance_copies and instanced.copyable
    return found


def instance_targets(instanced_name, instanced: Instanced) -> list:
    """The plan names of a supported instancer's instances, in order: 'Grid: Sphere #3', 'Grid: generated geometry
    #4' (a mesh made inside the node tree)."""
    return [f"{instanced_name}: {'generated geometry' if k in instanced.generated else source} #{k + 1}"
            for k, (source, _) in enumerate(instanced.entries)]


@dataclass
class BakeTarget:
    """One baked thing of a plan in the scene: an object, or one instance of an instanced object."""
    name: str
    obj: object  # whose surface and material slots it has (the instanced object for an instance)
    matrix: object  # its world matrix (mathutils.Matrix)
    instancer: object = None  # the object instancing it; None for an object of the scene itself


def bake_targets(scene, object_plans, depsgraph) -> list:
    """The BakeTarget of each ObjectPlan, found in the evaluated scene; one clear error where the scene changed (every
    object of the plan that is gone, an instance's instancer or instanced object included, named at once)."""
    from mathutils import Matrix

    missing = [o.name for o in object_plans if scene.objects.get(o.instancer or o.name) is None
               or (o.instancer and bpy.data.objects.get(o.source) is None)]
    if missing:
        raise BakeInputError(f"objects {missing} of the plan are not in scene '{scene.name}'; make a new plan")
    instancers, copies_by_instancer, targets = None, {}, []
    for plan in object_plans:
        instancer = scene.objects.get(plan.instancer) if plan.instancer else None
        if instancer is not None and copied(instancer):  # an object copy stands in for the instance
            if plan.instancer not in copies_by_instancer:  # looked up once per instancer, not once per instance
                copies_by_instancer[plan.instancer] = copies_of(instancer)
            copies = copies_by_instancer[plan.instancer]
            if plan.instance >= len(copies) or copies[plan.instance][INSTANCE_COPY_KEY]["source"] != plan.source:
                raise BakeInputError(f"'{plan.name}': the object copies of '{plan.instancer}''s instances changed "
                                     "since the plan; make a new plan")
            copy = copies[plan.instance]
            targets.append(BakeTarget(plan.name, copy, copy.matrix_world.copy()))
            continue
        if not plan.instancer:
            obj = scene.objects[plan.name]
            if obj.type in STAND_IN_TYPES:  # baked through its mesh stand-in, which the capture makes
                obj = stand_in_of(obj)
                if obj is None:
                    raise BakeInputError(f"'{plan.name}': its mesh stand-in is missing (the capture makes it); run "
                                         "the capture stage first")
            targets.append(BakeTarget(plan.name, obj, obj.matrix_world.copy()))
            continue
        instancers = instances_by_instancer(depsgraph) if instancers is None else instancers
        found = instancers.get(plan.instancer)
        if found is not None and found.copyable:
            raise BakeInputError(f"'{plan.name}': its object copy is missing (the capture makes it); run the capture "
                                 "stage first")
        if found is None or plan.instance >= len(found.entries) or found.entries[plan.instance][0] != plan.source:
            raise BakeInputError(f"'{plan.name}': the instances of '{plan.instancer}' changed since the plan; make a "
                                 "new plan")
        targets.append(BakeTarget(plan.name, bpy.data.objects[plan.source], Matrix(found.entries[plan.instance][1]),
                                  bpy.data.objects[plan.instancer]))
    return targets


def _instance_plans(instancer, instanced: Instanced, settings, depsgraph, surfaces_of) -> list:
    """One ObjectPlan per instance of a supported instancer: its source's materials, its area under its matrix."""
    plans, triangles = [], {}
    for k, (name, (source, matrix)) in enumerate(zip(instance_targets(instancer, instanced), instanced.entries)):
        obj = bpy.data.objects[source]
        if k in instanced.generated:  # node-made geometry: its own mesh and materials
            coords, verts, material_names = instanced.generated[k]
            _, mat_plans = surfaces_of(obj, [bpy.data.materials.get(n) for n in material_names] or [None])
            area = _area_under(matrix, coords, verts)
            source_type = "MESH"
        else:
            _, mat_plans = surfaces_of(obj)
            if source not in triangles:  # every instance of an object shares its evaluated surface
                triangles[source] = _evaluated_triangles(obj, depsgraph)
            area = _area_under(matrix, *triangles[source])
            source_type = obj.type
        glossy = [mp.name for mp in mat_plans if mp.glossy]
        lightmapped = [mp.name for mp in mat_plans if mp.irradiance_only]
        baked = bool(glossy or lightmapped) and area > 0 and source_type in MODIFIER_TYPES
        reason = "; ".join(([f"glossy material(s): {', '.join(glossy)}"] if glossy else [])
                           + ([f"irradiance lightmap: {', '.join(lightmapped)}"] if lightmapped else [])) or \
            "no glossy or lightmapped material: left to the renderer's own lighting"
        if source_type in STAND_IN_TYPES:
            reason = (f"left to the renderer: an instanced {GEOMETRY_KINDS[obj.type]} has no mesh stand-in (the "
                      f"{GEOMETRY_KINDS[obj.type]} itself, where it stands in the scene, bakes through one)")
        plans.append(ObjectPlan(name, round(area, 6), int(np.ceil(area * settings.texel_density**2)) if baked else 0,
                                baked, mat_plans, reason, f"{instanced.how} instance {k + 1} of {instanced.count}, "
                                f"of '{'generated geometry' if k in instanced.generated else source}' on "
                                f"'{instancer}'" + (", as an object copy" if instanced.copies else ""),
                                instancer=instancer, source=source, instance=k))
    return plans


def _why_no_surface(obj) -> str:
    if obj.type == "CURVE":
        return "no surface: a curve without bevel, extrusion or a profile renders nothing"
    if obj.type == "FONT":
        return "no surface: text without characters renders nothing"
    if obj.type == "META":
        return ("no surface of its own: a metaball's elements render as part of its family's base object (the one "
                "of the same name without a number suffix)")
    return "no faces with area"


def loop_triangle_arrays(mesh):
    """(loops (T, 3), vertices (T, 3), material index (T,), vertex coordinates (V, 3)) of a mesh's triangles."""
    mesh.calc_loop_triangles()
    count = len(mesh.loop_triangles)
    loops = np.empty(count * 3, np.int64)
    verts = np.empty(count * 3, np.int64)
    mat_index = np.empty(count, np.int64)
    mesh.loop_triangles.foreach_get("loops", loops)
    mesh.loop_triangles.foreach_get("vertices", verts)
    mesh.loop_triangles.foreach_get("material_index", mat_index)
    coords = np.empty(len(mesh.vertices) * 3, np.float64)
    mesh.vertices.foreach_get("co", coords)
    return loops.reshape(-1, 3), verts.reshape(-1, 3), mat_index, coords.reshape(-1, 3)


def transform_points(matrix, points):
    m = np.array(matrix, dtype=np.float64)
    return points @ m[:3, :3].T + m[:3, 3]


def triangle_areas(points, verts):
    a, b, c = (points[verts[:, k]] for k in range(3))
    return 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)


def _evaluated_triangles(obj, depsgraph):
    """(vertex coordinates (V, 3), triangles (T, 3)) of `obj`'s evaluated surface in object space; (None, None)
    when it has no faces."""
    if obj.type not in GEOMETRY_KINDS:  # a lamp, a camera, ... (a collection instance may hold one)
        return None, None
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        if mesh is None or len(mesh.polygons) == 0:
            return None, None
        _, verts, _, coords = loop_triangle_arrays(mesh)
        return coords, verts
    finally:
        evaluated.to_mesh_clear()


def _area_under(matrix, coords, verts) -> float:
    return 0.0 if coords is None else float(triangle_areas(transform_points(matrix, coords), verts).sum())


def _world_area(obj, depsgraph) -> float:
    return _area_under(obj.matrix_world, *_evaluated_triangles(obj, depsgraph))


def _uniform_colour_environment(color, black_reason: str) -> EnvironmentPlan:
    color = tuple(color)[:3]
    if max(color) <= 0:
        return EnvironmentPlan(False, "none", False, False, 0, black_reason)
    chromatic = (max(color) - min(color)) / max(color) > ACHROMATIC_CHROMA_MAX
    return EnvironmentPlan(True, "color", chromatic, True, 3 if chromatic else 1,
                           "uniform world colour: " + ("RGB" if chromatic else "mono") + " env visibility")


def analyse_environment(scene) -> EnvironmentPlan:
    world = scene.world
    if not uses_nodes(world):
        color = world.color if world is not None else (0.0, 0.0, 0.0)
        return _uniform_colour_environment(color, "no world: nothing to shadow")
    output = next((n for n in world.node_tree.nodes if n.type == "OUTPUT_WORLD" and n.is_active_output), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return EnvironmentPlan(False, "none", False, False, 0, "world has no surface shader")
    background = output.inputs["Surface"].links[0].from_node
    strength, linked_strength = _input_value(background, "Strength", 1.0)
    color_socket = background.inputs.get("Color")
    if not linked_strength and strength <= 0:
        return EnvironmentPlan(False, "none", False, False, 0, "world strength is 0: black environment")
    if color_socket is not None and color_socket.is_linked:
        source = color_socket.links[0].from_node
        if source.type == "TEX_ENVIRONMENT" and source.image is not None:
            chroma = _image_chroma(source.image)
            chromatic = chroma > ACHROMATIC_CHROMA_MAX
            return EnvironmentPlan(True, "hdri", chromatic, True, 3 if chromatic else 1,
                                   f"HDRI '{source.image.name}', chroma {chroma:.3f}: "
                                   + ("RGB" if chromatic else "mono") + " env visibility")
        return EnvironmentPlan(True, "hdri", True, True, 3, "procedural world: RGB env visibility")
    color = color_socket.default_value if color_socket is not None else (1.0, 1.0, 1.0)
    return _uniform_colour_environment(color, "world colour is black")


def _image_chroma(image) -> float:
    """Luminance-weighted mean of (max - min) / max over the image's finite, positive pixels."""
    pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    rgb = pixels.reshape(-1, image.channels)[:, :3].astype(np.float64)
    rgb = rgb[np.all(np.isfinite(rgb), axis=1)]
    rgb = np.maximum(rgb, 0)
    peak = rgb.max(axis=1)
    lum = rgb @ LUMINANCE
    valid = peak > 0
    if not np.any(valid):
        return 0.0
    chroma = (peak[valid] - rgb[valid].min(axis=1)) / peak[valid]
    return float(np.sum(chroma * lum[valid]) / max(np.sum(lum[valid]), 1e-30))


@contextlib.contextmanager
def active_scene(scene):
    """Make `scene` the window's scene for the block: only the active scene has an evaluated depsgraph
    (modifiers applied). The previous scene comes back afterwards, also on errors."""
    window = bpy.context.window
    previous = window.scene if window is not None else None
    if window is not None and previous != scene:
        window.scene = scene
    try:
        yield bpy.context.evaluated_depsgraph_get()
    finally:
        if window is not None and previous is not None and window.scene != previous:
            window.scene = previous


@contextlib.contextmanager
def quiet_stdout():
    """Cycles logs every render to the process's stdout (fd 1); machine-readable --json output and the
    progress bar must not be interleaved with it. Errors still reach stderr."""
    sys.stdout.flush()
    try:
        saved = os.dup(1)
    except OSError:  # no real fd 1 (some embedded consoles): nothing to silence
        yield
        return
    try:
        with open(os.devnull, "wb") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


# Data types whose surface renders at its own resolution: the settings (each with a render_ twin) to evaluate at.
_RESOLUTIONS = {"Curve": ("resolution_u",), "TextCurve": ("resolution_u",),
                "SurfaceCurve": ("resolution_u", "resolution_v"), "MetaBall": ("resolution",)}


def render_evaluation(objects):
    """Evaluate `objects` as a render does for the block: each modifier shown as for rendering, subdivision at its
    render levels, every particle and child particle a render makes, and curves, surfaces and metaballs (a
    stand-in's source too) at their render resolution (the viewport may show less). Every setting comes back
    afterwards."""
    return temporarily(_render_settings(objects))


def _render_settings(objects):
    """(owner, setting, value) of render_evaluation, each read when the one before it is made (data shared by two
    objects is changed once)."""
    for obj in objects:
        for modifier in getattr(obj, "modifiers", ()):
            if modifier.show_viewport != modifier.show_render:
                yield modifier, "show_viewport", modifier.show_render
            if modifier.type in ("SUBSURF", "MULTIRES") and modifier.levels != modifier.render_levels:
                yield modifier, "levels", modifier.render_levels
            if modifier.type == "PARTICLE_SYSTEM":  # every particle and child a render makes
                particles = modifier.particle_system.settings
                for name, value in (("display_percentage", 100), ("child_percent", particles.rendered_child_count)):
                    if getattr(particles, name) != value:
                        yield particles, name, value
        data = obj.parent.data if is_stand_in(obj) and obj.parent is not None else obj.data
        for name in _RESOLUTIONS.get(type(data).__name__, ()):
            render_value = getattr(data, f"render_{name}")
            if render_value and getattr(data, name) != render_value:  # 0: renders use the viewport's
                yield data, name, render_value


def build_plan(scene, settings: BakeSettings) -> BakePlan:
    """Analyse `scene` and decide what to bake. Raises BakeInputError with one clear message."""
    with active_scene(scene), render_evaluation([o for o in scene.objects if o.type in GEOMETRY_KINDS]):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        depsgraph.update()
        return _build_plan(scene, settings, depsgraph)


GEOMETRY_KINDS = {"MESH": "mesh", "CURVE": "curve", "FONT": "text", "SURFACE": "NURBS surface", "META": "metaball"}


def geometry_description(obj) -> str:
    """What the bake sees of an object: its kind and the modifiers that render, e.g. 'mesh + Bevel, Array'."""
    shown, off = user_modifiers(obj), modifiers_turned_off(obj)  # off: turned off by the instance copies, not the user
    modifiers = [m.name for m in getattr(obj, "modifiers", ()) if (m in shown and m.show_render) or m.name in off]
    return GEOMETRY_KINDS[obj.type] + (" + " + ", ".join(modifiers) if modifiers else "")


def _build_plan(scene, settings: BakeSettings, depsgraph) -> BakePlan:
    settings.validate()
    # A stand-in's source and an instance copy's instancer are planned, not what the bake added for them.
    visible = [o for o in scene.objects if not o.hide_render and not is_stand_in(o) and not is_copy(o)]
    shapes = [o for o in visible if o.type in GEOMETRY_KINDS]
    if not shapes:
        kinds = sorted({o.type.lower() for o in visible})
        raise BakeInputError("nothing to bake: the scene has no mesh, curve or text objects"
                             + (f" (only {', '.join(kinds)})" if kinds else " (it is empty)"))
    objects, emissive, warnings = [], [], []
    analysed, emits = {}, {}  # per material: its plan, and whether its surface emits (each surface analysed once)

    def surfaces_of(obj, mats=None):
        """(materials, their plans) of an object's slots, or of `mats` (node-made geometry's own)."""
        mats = mats if mats is not None else [slot.material for slot in obj.material_slots] or [None]
        for m in mats:
            if m not in analysed:
                original = unbaked(m)
                surface = analyse_surface(original) if original is not None else None
                analysed[m] = analyse_material(m, settings, surface)
                emits[m] = surface is not None and original.node_tree is not None and surface.emissive
        return mats, [analysed[m] for m in mats]

    every_instancer = scene_instancers(scene, depsgraph, settings)
    instances = dict(every_instancer)  # the ones not yet in the plan
    for obj in shapes:
        mats, mat_plans = surfaces_of(obj)
        if any(emits[m] for m in mats):
            emissive.append(obj.name)
        geometry = geometry_description(obj)
        instanced = instances.pop(obj.name, None)
        area = _world_area(obj, depsgraph)
        glossy = [mp.name for mp in mat_plans if mp.glossy]
        lightmapped = [mp.name for mp in mat_plans if mp.irradiance_only]
        baked = bool(glossy or lightmapped)
        if instanced is not None:
            geometry += f"; {instanced.description()}"
        if area <= 0:
            why = instanced.reason() if instanced is not None else _why_no_surface(obj)
            if baked and instanced is None:
                warnings.append(f"'{obj.name}': {why}: nothing of it is baked")
            objects.append(ObjectPlan(obj.name, 0.0, 0, False, mat_plans, why, geometry))
            continue
        texels = int(np.ceil(area * settings.texel_density**2)) if baked else 0
        reason = "; ".join(([f"glossy material(s): {', '.join(glossy)}"] if glossy else [])
                           + ([f"irradiance lightmap: {', '.join(lightmapped)}"] if lightmapped else [])) \
            or "no glossy or lightmapped material: not baked, left to the renderer's own lighting (" + \
            "; ".join(f"{mp.name}: {mp.reason}" for mp in mat_plans) + ")"
        if instanced is not None:
            reason += f"; {instanced.reason()}"
        if baked and obj.type in STAND_IN_TYPES:
            reason += (f"; through a mesh stand-in that follows its surface (a {GEOMETRY_KINDS[obj.type]} takes no "
                       "modifiers): the stand-in renders in its place, the original is invisible to rays and probes "
                       "and drawn as wire until Remove SG Bake")
        objects.append(ObjectPlan(obj.name, round(area, 6), texels, baked, mat_plans, reason, geometry))
    for name, instanced in sorted(instances.items()):  # empties instancing collections, and the like
        objects.append(ObjectPlan(name, 0.0, 0, False, [], instanced.reason(), instanced.description()))
    for name, instanced in every_instancer.items():
        if not instanced.unsupported():
            objects += _instance_plans(name, instanced, settings, depsgraph, surfaces_of)
    glossy_instances = sorted({source for o in every_instancer.values() if o.unsupported() for source in o.sources
                               if bpy.data.objects.get(source) is not None and any(
                                   plan.glossy for plan in surfaces_of(bpy.data.objects[source])[1])})
    for obj in objects:
        instancers = sorted(name for name, o in every_instancer.items() if o.unsupported()
                            and obj.bake_lightfield and obj.name in o.sources and name != obj.name)
        if instancers:
            warnings.append(f"'{obj.name}' is baked and also instanced by {', '.join(instancers)}: its instances show "
                            f"the lighting baked where '{obj.name}' itself stands")
    if glossy_instances:
        copyable = any(o.copyable and not o.copies for o in every_instancer.values())
        warnings.append("instances of glossy objects are not baked: " + ", ".join(glossy_instances)
                        + "; each keeps the renderer's own lighting (the plan says why"
                        + ("; Instances as Copies bakes them as object copies" if copyable else "") + ")")
    if not any(o.bake_lightfield for o in objects):
        left = sorted({mp.name for o in objects for mp in o.materials if mp.reason.startswith("left to the renderer")})
        raise BakeInputError("nothing to bake: no object or instance has a glossy material (roughness below "
                             f"{GLOSSY_ROUGHNESS_MAX}) or a rough one to lightmap; the light field would not be used"
                             + (f" (left to the renderer: {', '.join(left)}; see the plan for why)" if left else "")
                             + (f"; {warnings[-1]}" if glossy_instances else ""))
    lamps = [o.name for o in visible if o.type == "LIGHT" and o.data.energy > 0]
    hair = [o.name for o in visible if o.type == "CURVES"]
    environment = analyse_environment(scene)
    if environment.iwev and not any(m.glossy for o in objects if o.bake_lightfield for m in o.materials):
        environment.iwev, environment.iwev_channels = False, 0
        environment.reason += "; env visibility off: no glossy material (the irradiance lightmaps hold the sky)"
    if not lamps and not emissive and not environment.present:
        warnings.append("no lamps, emissive meshes or environment: the bake will be black")
    return BakePlan(scene=scene.name, settings=settings, objects=objects, environment=environment, lamps=lamps,
                    emissive_objects=emissive, hair_objects=hair, warnings=warnings)
