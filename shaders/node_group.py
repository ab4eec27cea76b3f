"""Builder of the "SG Lightfield" shader node group (bpy is imported only when building).

The group evaluates shaders/sg_shading.py with every operation turned into one Blender shader node that
EEVEE and Cycles both support (Math, Vector Math, Clamp, Image Texture, Geometry; no OSL), so the numpy
reference (`shade(NumpyOps(), ...)`) is the group's exact formula. What repeats per SG (the glossy of one SG, one
bilinear tile lookup) is a nested group built once and instanced (`NodeOps.call`): 16 SGs build in about 2 s
instead of 35 s flat, and the renderers flatten it back into the same graph.

Texture layout (one RGBA half-float image, `SGTextureLayout`): the lightmap atlas repeated as tiles in a
grid; tile 'sg' j = (axis xyz, log-encoded sharpness), 'amp' j = (rgb amplitude, 0), 'irradiance' = (rgb, 1), 'iwev' j
and 'iwev_amp' j likewise; the SH baseline has 'sh' j = (rgb coefficient, 0) instead of 'sg' and 'amp'.
Bilinear filtering is done by the nodes from four 'Closest' lookups: EEVEE samples 'Linear' image textures
through mipmaps, and coarse mip levels average neighbouring tiles (measured: colour garbage on the baked spheres).
The four texel corners and weights are computed once per material and clamped inside the atlas, so a lookup
never reaches into the next tile, in Cycles and EEVEE alike.

Versioned and idempotent: a group with the same name and version is updated in place (its users keep it);
`GROUP_VERSION` changes whenever the formula or the interface changes.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

from .sg_shading import shade

GROUP_NAME = "SG Lightfield"
GROUP_VERSION = 5  # 5: a Metallic input (the Fresnel's shape); 4: an Irradiance output (E / pi) for Diffuse BSDFs
VERSION_KEY = "sglf_version"
COLUMN_NODES = 40  # nodes per column in the automatic layout


@dataclass
class SGTextureLayout:
    sg_count: int
    iwev_count: int = 0
    has_irradiance: bool = True
    atlas_size: tuple = (1, 1)  # (width, height) of one tile in texels
    tiles: list = field(default_factory=list)  # [(name, j)] in tile order
    sh_count: int = 0  # SH L2 coefficient tiles 'sh' j instead of SGs (the benchmark's SH baseline)
    # > 1: the irradiance is an image of its own with this many pixels per texel (irradiance_detail.py), not a tile
    irradiance_detail: int = 1

    def __post_init__(self):
        if not self.tiles:
            self.tiles = [(kind, j) for j in range(self.sg_count) for kind in ("sg", "amp")]
            self.tiles += [("sh", j) for j in range(self.sh_count)]
            if self.has_irradiance and self.irradiance_detail <= 1:
                self.tiles.append(("irradiance", 0))
            self.tiles += [(kind, j) for j in range(self.iwev_count) for kind in ("iwev", "iwev_amp")]

    @property
    def grid(self) -> tuple[int, int]:
        columns = max(1, math.ceil(math.sqrt(len(self.tiles))))
        return columns, max(1, math.ceil(len(self.tiles) / columns))

    def tile_offset(self, name: str, j: int) -> tuple[int, int]:
        """(column, row from the bottom) of a tile, in tile units."""
        index = self.tiles.index((name, j))
        columns, rows = self.grid
        return index % columns, rows - 1 - index // columns

    def to_dict(self):
        return {"sg_count": self.sg_count, "sh_count": self.sh_count, "iwev_count": self.iwev_count,
                "has_irradiance": self.has_irradiance, "irradiance_detail": self.irradiance_detail,
                "atlas_size": list(self.atlas_size), "tiles": [list(t) for t in self.tiles]}


SOCKET_TYPES = {"VALUE": "NodeSocketFloat", "VECTOR": "NodeSocketVector", "RGBA": "NodeSocketColor"}
ZERO_INPUT = "zero"  # a nested group's input carrying the computed 0 its constants are made from
UNIFORM_BLOCK_LIMIT = 65536  # bytes of EEVEE's per-material uniform block ("node_tree"); also desktop GPUs' usual limit


class Vec(tuple):
    """A vector of the node backend kept as its three components (sockets or numbers)."""

    __slots__ = ()


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def socket_type(value) -> str:
    """Interface socket type for a NodeOps value: an output socket, a Python number, a 3-tuple or a Vec."""
    if _is_number(value):
        return "NodeSocketFloat"
    if isinstance(value, tuple):
        return "NodeSocketVector"
    return SOCKET_TYPES[value.type]


class NodeOps:
    """sg_shading operations as shader nodes.

    EEVEE gives a material one uniform block of at most 64 KiB, and every input of a node's GLSL function that no
    computed value feeds takes a slot in it: an unlinked socket, one fed by a Value node or by nodes Blender folds
    because they only see constants, and the unused inputs of a node too (the third of a binary Math node, the
    second and third vectors of Vector Math's Normalize). Measured on the baked courtyard: 125168 bytes at 16 SGs,
    so EEVEE drew its materials magenta (docs/design-additions.md section 14). So with `linked_constants` this
    backend feeds every input from a computed value:
    - vectors are kept as their components (Vec) and vector arithmetic is scalar MULTIPLY_ADD (a*b+c), the one
      Math operation that uses all three inputs; the rest (divide, min, max, exp, sqrt, ...) leave 1-2 floats;
    - a constant is computed once per tree from a per-pixel zero (anchor - anchor at the top, a 'zero' input in a
      nested group), so Blender cannot fold it, and linked from there to every use (4 bytes per constant and tree
      instance: cheaper in build time than passing each constant into every instance).
    Without `linked_constants` (Cycles-only trees, e.g. the hair reference), constants are socket values.
    """

    def __init__(self, tree, subgroups=None, *, anchor=None, group_input=None, linked_constants=None):
        self.tree = tree
        self.count = 0
        self.gate = None  # a non-negative value later texture lookups are made to depend on
        self.subgroups = {} if subgroups is None else subgroups  # call name -> (nested group, takes a 'zero')
        self.linked_constants = (anchor is not None or group_input is not None) if linked_constants is None \
            else linked_constants
        self.anchor = anchor  # top level: a scalar socket that varies per pixel (the zero is made from it)
        self.group_input = group_input  # nested group: its Group Input node (its 'zero' arrives there)
        self._constants = {}  # value -> socket
        self._zero = None
        self._split = {}  # vector socket pointer -> Vec of its components
        self._combined = {}  # Vec key -> CombineXYZ output

    # -- nodes, links and constants --------------------------------------------------------------------------

    def _node(self, kind, **props):
        node = self.tree.nodes.new(kind)
        for key, value in props.items():
            setattr(node, key, value)
        node.location = (200 * (self.count // COLUMN_NODES), -120 * (self.count % COLUMN_NODES))
        node.hide = True
        self.count += 1
        return node

    def zero(self):
        """A computed 0 (anchor - anchor), or the number 0 without linked constants."""
        if not self.linked_constants:
            return 0.0
        if self._zero is None:
            if self.group_input is not None:
                self.tree.interface.new_socket(ZERO_INPUT, in_out="INPUT", socket_type="NodeSocketFloat")
                self._zero = self.group_input.outputs[ZERO_INPUT]
            else:
                node = self._node("ShaderNodeMath", operation="SUBTRACT")
                self.tree.links.new(self.anchor, node.inputs[0])
                self.tree.links.new(self.anchor, node.inputs[1])
                self._zero = node.outputs[0]
        return self._zero

    def constant_socket(self, value: float):
        """The computed socket that carries `value` in this tree (made on first use)."""
        value = float(value)
        if value not in self._constants:
            if value == 0.0:
                self._constants[value] = self.zero()
            else:
                node = self._node("ShaderNodeMath", operation="MULTIPLY_ADD")
                self.tree.links.new(self.zero(), node.inputs[0])
                self.tree.links.new(self.zero(), node.inputs[1])
                node.inputs[2].default_value = value
                self._constants[value] = node.outputs[0]
        return self._constants[value]

    def launder(self, value):
        """`value` passed through one node fed by the computed zero: what depends on it can no longer be folded
        into per-use uniforms when a material leaves the group's input unlinked. Vec in, Vec out."""
        if not self.linked_constants:
            return value
        if isinstance(value, tuple) or getattr(value, "type", "VALUE") != "VALUE":
            return Vec(self._math("MULTIPLY_ADD", x, 1.0, self.zero()) for x in self._vec(value))
        return self._math("MULTIPLY_ADD", value, 1.0, self.zero())

    def _feed(self, socket, value):
        if hasattr(value, "is_linked"):  # a socket (not `links`: that property scans every link of the tree)
            self.tree.links.new(value, socket)
        elif isinstance(value, tuple):
            if self.linked_constants or not all(_is_number(v) for v in value):
                self.tree.links.new(self.vector_socket(value), socket)
            else:
                socket.default_value = (*value, 1.0)[:len(socket.default_value)]
        elif self.linked_constants:
            self.tree.links.new(self.constant_socket(value), socket)
        else:
            socket.default_value = value

    def _math(self, operation, *values):
        node = self._node("ShaderNodeMath", operation=operation)
        for socket, value in zip(node.inputs, values):
            self._feed(socket, value)
        return node.outputs[0]

    def _vec(self, value) -> Vec:
        """The components of a vector value (Vec, tuple or vector/colour socket; a socket is split once)."""
        if isinstance(value, Vec):
            return value
        if isinstance(value, tuple):
            return Vec(float(v) for v in value[:3])
        key = value.as_pointer()
        if key not in self._split:
            node = self._node("ShaderNodeSeparateXYZ")
            self.tree.links.new(value, node.inputs[0])
            self._split[key] = Vec(node.outputs[:3])
        return self._split[key]

    def vector_socket(self, value):
        """A vector socket carrying `value` (Vec components are combined once)."""
        if not isinstance(value, tuple):
            return value
        value = self._vec(value)
        key = tuple(("number", v) if _is_number(v) else v.as_pointer() for v in value)
        if key not in self._combined:
            node = self._node("ShaderNodeCombineXYZ")
            for socket, component in zip(node.inputs, value):
                self._feed(socket, component)
            self._combined[key] = node.outputs[0]
        return self._combined[key]

    def barrier(self, value):
        """Make later texture lookups depend on `value` (>= 0) by adding min(value, 0) = 0 to their UVs. Cycles' SVM
        compiler otherwise schedules every lookup of the graph first and runs out of its 255-slot stack (measured:
        "out of SVM stack space" and black materials at N = 8 with IWEV)."""
        if isinstance(value, tuple):
            value = next((v for v in self._vec(value) if not _is_number(v)), None)
        self.gate = None if value is None or _is_number(value) else self.minimum(value, 0.0)

    def call(self, name, function, **inputs):
        """function(ops, **inputs) -> {output: value} as one Group node. The nested group `<tree name> / name` is
        built on the first call and instanced after that: each node and link bpy adds costs time that grows with the
        tree's size, so one flat group takes time quadratic in its size (measured: 0.4 s for 500 Math nodes, 18 s
        for 2000), while the renderers flatten nested groups back into the same graph."""
        if name not in self.subgroups:
            self.subgroups[name] = self._build_subgroup(f"{self.tree.name} / {name}", function, inputs)
        group, takes_zero = self.subgroups[name]
        node = self._node("ShaderNodeGroup", node_tree=group)
        for key, value in inputs.items():
            self._feed(node.inputs[key], value)
        if takes_zero:
            self._feed(node.inputs[ZERO_INPUT], self.zero())
        return {socket.name: socket for socket in node.outputs}

    def _build_subgroup(self, name, function, inputs):
        group = new_or_cleared_group(name)
        for key, value in inputs.items():
            group.interface.new_socket(key, in_out="INPUT", socket_type=socket_type(value))
        group_inputs = self._node_in(group, "NodeGroupInput")
        ops = NodeOps(group, self.subgroups, group_input=group_inputs if self.linked_constants else None,
                      linked_constants=self.linked_constants)
        ops.count = 1
        outputs = function(ops, **{key: group_inputs.outputs[key] for key in inputs})
        for key, value in outputs.items():
            group.interface.new_socket(key, in_out="OUTPUT", socket_type=socket_type(value))
        group_outputs = ops._node("NodeGroupOutput")
        for key, value in outputs.items():
            ops._feed(group_outputs.inputs[key], value)
        group[VERSION_KEY] = GROUP_VERSION
        return group, ops._zero is not None and self.linked_constants

    @staticmethod
    def _node_in(tree, kind):
        node = tree.nodes.new(kind)
        node.hide = True
        return node

    # -- scalar operations (numbers are folded here; Blender semantics: x / 0 = 0, sqrt of a negative = 0) -----

    def const(self, value):
        return float(value)

    def vconst(self, value):
        return Vec(float(v) for v in value)

    def muladd(self, a, b, c):
        """a * b + c."""
        if (_is_number(a) and a == 0.0) or (_is_number(b) and b == 0.0):
            return c
        if _is_number(a) and _is_number(b):
            a, b = a * b, 1.0
        if _is_number(b) and b == 1.0:
            if _is_number(a) and _is_number(c):
                return a + c
            if _is_number(c) and c == 0.0:
                return a
        return self._math("MULTIPLY_ADD", a, b, c)

    def add(self, a, b):
        if _is_number(a) and not _is_number(b):
            a, b = b, a
        return self.muladd(a, 1.0, b)

    def sub(self, a, b):
        if _is_number(b):
            return self.add(a, -b)
        return self.muladd(b, -1.0, a)

    def mul(self, a, b):
        return self.muladd(a, b, 0.0)

    def div(self, a, b):
        if _is_number(a) and _is_number(b):
            return a / b if b != 0 else 0.0
        if _is_number(b):
            return self.mul(a, 1.0 / b if b != 0 else 0.0)
        return self._math("DIVIDE", a, b)

    def maximum(self, a, b):
        return max(a, b) if _is_number(a) and _is_number(b) else self._math("MAXIMUM", a, b)

    def minimum(self, a, b):
        return min(a, b) if _is_number(a) and _is_number(b) else self._math("MINIMUM", a, b)

    def clamp(self, a, lo, hi):
        if _is_number(a):
            return min(max(a, lo), hi)
        node = self._node("ShaderNodeClamp", clamp_type="MINMAX")
        self._feed(node.inputs["Value"], a)
        self._feed(node.inputs["Min"], float(lo))
        self._feed(node.inputs["Max"], float(hi))
        return node.outputs[0]

    def exp(self, a):
        return math.exp(a) if _is_number(a) else self._math("EXPONENT", a)

    def sqrt(self, a):
        return math.sqrt(max(a, 0.0)) if _is_number(a) else self._math("SQRT", a)

    def floor(self, a):
        return math.floor(a) if _is_number(a) else self._math("FLOOR", a)

    def sin(self, a):
        return math.sin(a) if _is_number(a) else self._math("SINE", a)

    def acos(self, a):
        return math.acos(min(max(a, -1.0), 1.0)) if _is_number(a) else self._math("ARCCOSINE", a)

    def power(self, a, exponent):
        return self._math("POWER", a, float(exponent))

    # -- vector operations, component by component ------------------------------------------------------------

    def dot(self, a, b):
        total = 0.0
        for x, y in zip(self._vec(a), self._vec(b)):
            total = self.muladd(x, y, total)
        return total

    def cross(self, a, b):
        (ax, ay, az), (bx, by, bz) = self._vec(a), self._vec(b)
        return Vec(self.muladd(self.mul(p, q), -1.0, self.mul(r, s))
                   for r, s, p, q in ((ay, bz, az, by), (az, bx, ax, bz), (ax, by, ay, bx)))

    def normalize(self, a):
        a = self._vec(a)
        inverse_length = self.div(1.0, self.sqrt(self.dot(a, a)))  # 0 for the zero vector, as Blender's node
        return Vec(self.mul(x, inverse_length) for x in a)

    def _componentwise(self, scalar, a, b):
        return Vec(scalar(x, y) for x, y in zip(self._vec(a), self._vec(b)))

    def vadd(self, a, b):
        return self._componentwise(self.add, a, b)

    def vsub(self, a, b):
        return self._componentwise(self.sub, a, b)

    def vmul(self, a, b):  # componentwise
        return self._componentwise(self.mul, a, b)

    def vscale(self, a, s):
        if _is_number(s) and s == 1.0:
            return a
        return Vec(self.mul(x, s) for x in self._vec(a))

    def vmax(self, a, b):
        return self._componentwise(self.maximum, a, b)

    def vmin(self, a, b):
        return self._componentwise(self.minimum, a, b)


def flattened_node_count(tree) -> int:
    """Nodes of `tree` with every nested group expanded: the size of the graph the renderers compile."""
    return sum(flattened_node_count(node.node_tree) if node.bl_idname == "ShaderNodeGroup" and node.node_tree
               else 1 for node in tree.nodes)


def new_or_cleared_group(name: str):
    """The shader node group `name`, emptied (its users keep it), or a new one."""
    import bpy

    group = bpy.data.node_groups.get(name)
    if group is None or group.bl_idname != "ShaderNodeTree":
        group = bpy.data.node_groups.new(name, "ShaderNodeTree")
    group.nodes.clear()
    group.interface.clear()
    return group


def closest_texture(tree, image):
    """An Image Texture node reading `image` at the nearest texel, clamped at the edges. Its texture mapping is
    refreshed once: a node made from Python keeps an identity mapping that Blender has not yet flagged as one, and
    EEVEE then evaluates that 4x4 matrix from 88-96 bytes of uniforms per node (measured)."""
    node = tree.nodes.new("ShaderNodeTexImage")
    node.image, node.interpolation, node.extension = image, "Closest", "EXTEND"
    node.texture_mapping.translation = node.texture_mapping.translation  # its update sets the unit-matrix flag
    node.hide = True
    return node


def _bilinear_corners(ops, u, v, width: float, height: float) -> dict:
    """The four texel centres around (u, v) in an image of width x height texels (clamped inside it) and their
    bilinear weights: {'corner i': Vec, 'weight i': value}, i over (0, 0), (1, 0), (0, 1), (1, 1)."""
    texel_x, texel_y = ops.sub(ops.mul(u, width), 0.5), ops.sub(ops.mul(v, height), 0.5)
    base_x, base_y = ops.floor(texel_x), ops.floor(texel_y)
    tx, ty = ops.sub(texel_x, base_x), ops.sub(texel_y, base_y)
    corners = {}
    for i, (dx, dy) in enumerate(((0, 0), (1, 0), (0, 1), (1, 1))):
        cx = ops.clamp(ops.mul(ops.add(base_x, dx + 0.5), 1.0 / width), 0.5 / width, 1 - 0.5 / width)
        cy = ops.clamp(ops.mul(ops.add(base_y, dy + 0.5), 1.0 / height), 0.5 / height, 1 - 0.5 / height)
        corners[f"corner {i}"] = Vec((cx, cy, 0.0))
        corners[f"weight {i}"] = ops.mul(tx if dx else ops.sub(1.0, tx), ty if dy else ops.sub(1.0, ty))
    return corners


def _bilinear_lookup(image, columns: int, rows: int):
    """The nested group's function: the four 'Closest' lookups of the tile of `image` (a grid of columns x rows
    tiles) whose corner is (offset_x, offset_y), blended: {'colour', 'alpha'}. `gate` is 0, computed from what the
    lookups must wait for (NodeOps.barrier). 'Closest' keeps renderers from mipmapping: a mip level averages
    neighbouring tiles (colour garbage), and across a chart seam EEVEE's UV derivatives pick the coarsest level
    (dotted dark seams, measured on the detail image with 'Linear')."""
    def bilinear_tile(tile_ops, offset_x, offset_y, gate, **corner_sockets):
        offset_x = tile_ops.add(offset_x, gate)
        colour, alpha = Vec((0.0, 0.0, 0.0)), 0.0
        for i in range(4):
            corner = tile_ops._vec(corner_sockets[f"corner {i}"])
            uv_in_image = Vec((tile_ops.muladd(corner[0], 1.0 / columns, offset_x),
                               tile_ops.muladd(corner[1], 1.0 / rows, offset_y), 0.0))
            texture = closest_texture(tile_ops.tree, image)
            tile_ops.tree.links.new(tile_ops.vector_socket(uv_in_image), texture.inputs["Vector"])
            weight = corner_sockets[f"weight {i}"]
            colour = Vec(tile_ops.muladd(x, weight, total)
                         for x, total in zip(tile_ops._vec(texture.outputs["Color"]), colour))
            alpha = tile_ops.muladd(texture.outputs["Alpha"], weight, alpha)
        return {"colour": colour, "alpha": alpha}

    return bilinear_tile


def build_node_group(image, layout: SGTextureLayout, env_sgs=(), name: str = GROUP_NAME, irradiance_image=None):
    """Create or update the node group and its nested groups (`<name> / ...`); returns it. `image` is the packed SG
    image (Non-Color, half float); `irradiance_image` the irradiance detail image when layout.irradiance_detail > 1.
    The group computes the same in both renderers."""
    if layout.has_irradiance and layout.irradiance_detail > 1 and irradiance_image is None:
        raise ValueError("the layout reads an irradiance detail image; pass it as irradiance_image")
    group = new_or_cleared_group(name)
    sockets = [("UV", "INPUT", "NodeSocketVector"), ("Normal", "INPUT", "NodeSocketVector"),
               ("Roughness", "INPUT", "NodeSocketFloat"), ("F0", "INPUT", "NodeSocketColor"),
               ("Albedo", "INPUT", "NodeSocketColor"), ("Metallic", "INPUT", "NodeSocketFloat"),
               ("Total", "OUTPUT", "NodeSocketColor"),
               ("Glossy", "OUTPUT", "NodeSocketColor"), ("Diffuse", "OUTPUT", "NodeSocketColor"),
               ("Environment", "OUTPUT", "NodeSocketColor"), ("Irradiance", "OUTPUT", "NodeSocketColor")]
    for socket_name, in_out, socket_type_name in sockets:
        group.interface.new_socket(socket_name, in_out=in_out, socket_type=socket_type_name)
    inputs = NodeOps._node_in(group, "NodeGroupInput")
    geometry = NodeOps._node_in(group, "ShaderNodeNewGeometry")
    position = NodeOps._node_in(group, "ShaderNodeSeparateXYZ")
    group.links.new(geometry.outputs["Position"], position.inputs[0])
    ops = NodeOps(group, anchor=position.outputs["X"])
    ops.count = 3
    # The material may leave these unlinked (constants): laundered so nothing downstream folds into uniforms.
    uv, normal, f0, albedo = (ops.launder(inputs.outputs[key]) for key in ("UV", "Normal", "F0", "Albedo"))
    roughness, metallic = (ops.launder(inputs.outputs[key]) for key in ("Roughness", "Metallic"))
    columns, rows = layout.grid
    width, height = (float(v) for v in layout.atlas_size)
    # Shared by every tile: the four texel centres around UV (clamped inside the atlas) and their weights.
    u, v, _ = ops._vec(uv)
    corner_inputs = _bilinear_corners(ops, u, v, width, height)
    bilinear_tile = _bilinear_lookup(image, columns, rows)

    cache = {}

    def lookup(kind, j):
        if (kind, j) == ("irradiance", 0) and layout.irradiance_detail > 1 and ("irradiance", 0) not in cache:
            # its own four texel centres, at `irradiance_detail` times the atlas' resolution
            detail = layout.irradiance_detail
            gate = ops.gate if ops.gate is not None else ops.zero()
            tile = ops.call("bilinear detail", _bilinear_lookup(irradiance_image, 1, 1), offset_x=0.0, offset_y=0.0,
                            gate=gate, **_bilinear_corners(ops, u, v, width * detail, height * detail))
            cache[(kind, j)] = (tile["colour"], tile["alpha"])
        if (kind, j) not in cache:
            col, row = layout.tile_offset(kind, j)
            gate = ops.gate if ops.gate is not None else ops.zero()  # 0, once the previous SG is done
            tile = ops.call("bilinear tile", bilinear_tile, offset_x=col / columns, offset_y=row / rows, gate=gate,
                            **corner_inputs)
            cache[(kind, j)] = (tile["colour"], tile["alpha"])
        return cache[(kind, j)]

    result = shade(ops, lookup, normal, geometry.outputs["Incoming"], roughness, f0, albedo, layout.sg_count,
                   layout.iwev_count, [tuple(e) for e in env_sgs], layout.has_irradiance, layout.sh_count, metallic)
    outputs = ops._node("NodeGroupOutput")
    outputs.location = (200 * (ops.count // COLUMN_NODES + 1), 0)
    for key, socket_name in (("total", "Total"), ("glossy", "Glossy"), ("diffuse", "Diffuse"),
                             ("environment", "Environment"), ("irradiance", "Irradiance")):
        ops._feed(outputs.inputs[socket_name], result[key])
    group[VERSION_KEY] = GROUP_VERSION
    group["sglf_layout"] = str(layout.to_dict())
    group["sglf_has_environment"] = bool(env_sgs) and layout.iwev_count > 0  # else its Environment output is black
    return group


_UNIFORM_FLOATS = {"VALUE": 1, "INT": 1, "BOOLEAN": 1, "VECTOR": 3, "RGBA": 4}
_NON_CONSTANT_SOURCES = {"ShaderNodeNewGeometry", "ShaderNodeUVMap", "ShaderNodeAttribute", "ShaderNodeTexImage",
                         "ShaderNodeTexCoord", "ShaderNodeObjectInfo", "ShaderNodeLightPath", "ShaderNodeCameraData"}


def _node_table(tree, tables):
    """Per node of `tree`: (bl_idname, nested tree, identity texture mapping, [(input identifier, type, enabled,
    feeding (node, output identifier) or None)]), keyed by node pointer; plus the active group output. Read once."""
    key = tree.as_pointer()
    if key not in tables:
        feeds = {}
        for link in tree.links:
            if link.is_valid and not link.is_muted:
                feeds[(link.to_node.as_pointer(), link.to_socket.identifier)] = (link.from_node.as_pointer(),
                                                                                 link.from_socket.identifier)
        nodes, group_output = {}, None
        for node in tree.nodes:
            pointer = node.as_pointer()
            identity = True
            if node.bl_idname == "ShaderNodeTexImage":
                m = node.texture_mapping
                identity = (tuple(m.translation) == (0, 0, 0) and tuple(m.rotation) == (0, 0, 0)
                            and tuple(m.scale) == (1, 1, 1) and not m.use_min and not m.use_max)
            if node.bl_idname == "NodeGroupOutput" and node.is_active_output:
                group_output = pointer
            inputs = [(s.identifier, s.type, s.enabled, feeds.get((pointer, s.identifier))) for s in node.inputs]
            nodes[pointer] = (node.bl_idname, getattr(node, "node_tree", None), identity, inputs)
        tables[key] = (nodes, group_output)
    return tables[key]


def material_output(tree, renderer: str):
    """The Material Output node `renderer` ('EEVEE' or 'CYCLES') uses, as Blender picks it
    (ntreeShaderOutputNode): one for that renderer before one for all, the active one first among equals."""
    best = None
    for node in tree.nodes:
        if node.bl_idname != "ShaderNodeOutputMaterial" or node.target not in ("ALL", renderer):
            continue
        if best is None or (node.target == renderer and best.target == "ALL") or \
                (node.target == best.target and node.is_active_output and not best.is_active_output):
            best = node
    return best


def eevee_uniform_bytes(material) -> dict:
    """The size EEVEE gives `material`'s uniform block ("node_tree", at most UNIFORM_BLOCK_LIMIT bytes; beyond it the
    shader does not link and the material renders magenta), counted from its node graph with the nested groups
    expanded, as Blender 5.0's GPU code generation makes it (gpu_node_graph.cc, gpu_codegen.cc):
    - every float/vector/colour input of a node that reaches the surface output takes a uniform, unavailable ones
      included, unless a node that computes something feeds it; a Value node, or a node whose inputs are all
      constants (which Blender folds), counts as a constant;
    - an Image Texture node adds its mapping matrix (4 vec4 + 2 vec3) unless its mapping is the identity (the
      builder's nodes have Blender's identity flag refreshed, `closest_texture`; a Python-made node without that
      refresh is counted too low);
    - vec4s and vec3s take 16 bytes each, floats fill the vec3s' fourth slots first, plus the cryptomatte float.
    Checked against the size Blender reports when a shader fails (tests/test_apply.py). Returns
    {'bytes', 'floats', 'vec3', 'vec4', 'fits'}."""
    counts = {1: 0, 3: 0, 4: 0}
    tables, constant_memo, seen = {}, {}, set()

    def source(tree, feed, ctx):
        """(tree, node pointer, ctx) of the node computing what a link `feed` = (node, output identifier) carries,
        through reroutes and group boundaries; None when it ends at an unlinked group input."""
        while feed is not None:
            nodes, _ = _node_table(tree, tables)
            pointer, identifier = feed
            kind, nested, _, inputs = nodes[pointer]
            if kind == "NodeReroute":
                feed = inputs[0][3]
            elif kind == "NodeGroupInput":
                if not ctx:
                    return None
                (tree, group_pointer), ctx = ctx[-1], ctx[:-1]
                group_inputs = _node_table(tree, tables)[0][group_pointer][3]
                feed = next((f for ident, _, enabled, f in group_inputs if ident == identifier and enabled), None)
            elif kind == "ShaderNodeGroup":
                if nested is None:
                    return None
                nested_nodes, output = _node_table(nested, tables)
                if output is None:
                    return None
                ctx = ctx + ((tree, pointer),)
                tree = nested
                feed = next((f for ident, _, _, f in nested_nodes[output][3] if ident == identifier), None)
            else:
                return tree, pointer, ctx
        return None

    def context_key(tree, pointer, ctx):
        return pointer, tuple(p for _, p in ctx)

    def is_constant(tree, pointer, ctx):
        """Whether the node computes only from constants (iteratively: user graphs can be thousands deep)."""
        stack = [(tree, pointer, ctx)]
        while stack:
            tree_, pointer_, ctx_ = stack[-1]
            key = context_key(tree_, pointer_, ctx_)
            if key in constant_memo:
                stack.pop()
                continue
            kind, _, _, inputs = _node_table(tree_, tables)[0][pointer_]
            if kind in _NON_CONSTANT_SOURCES:
                constant_memo[key] = False
                stack.pop()
                continue
            feeding = [found for _, _, enabled, feed in inputs if enabled
                       and (found := source(tree_, feed, ctx_)) is not None]
            pending = [found for found in feeding if context_key(*found) not in constant_memo]
            if pending:
                stack.extend(pending)
                continue
            constant_memo[key] = all(constant_memo[context_key(*found)] for found in feeding)
            stack.pop()
        return constant_memo[context_key(tree, pointer, ctx)]

    def visit(tree, pointer, ctx):
        stack = [(tree, pointer, ctx)]
        while stack:
            tree, pointer, ctx = stack.pop()
            key = context_key(tree, pointer, ctx)
            if key in seen:
                continue
            seen.add(key)
            kind, _, identity, inputs = _node_table(tree, tables)[0][pointer]
            if not identity:
                counts[4] += 4
                counts[3] += 2
            for identifier, socket_type_name, enabled, feed in inputs:
                found = source(tree, feed, ctx) if enabled else None
                if found is not None and not is_constant(*found):
                    stack.append(found)
                elif socket_type_name in _UNIFORM_FLOATS and not (kind == "ShaderNodeTexImage"
                                                                  and identifier == "Vector"):
                    counts[_UNIFORM_FLOATS[socket_type_name]] += 1  # an unlinked texture Vector is the UV map

    tree = material.node_tree
    nodes, _ = _node_table(tree, tables)
    output = material_output(tree, "EEVEE")
    if output is not None:
        for identifier, _, enabled, feed in nodes[output.as_pointer()][3]:
            found = source(tree, feed, ()) if enabled else None
            if found is not None:
                visit(*found)
    floats, vec3, vec4 = counts[1] + 1, counts[3], counts[4]  # + the cryptomatte hash
    size = 16 * (vec4 + vec3) + 4 * max(0, floats - vec3)
    size = (size + 15) // 16 * 16
    return {"bytes": size, "floats": floats, "vec3": vec3, "vec4": vec4, "fits": size <= UNIFORM_BLOCK_LIMIT}
