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

try:
    from .sg_shading import shade
except ImportError:
    from shaders.sg_shading import shade

GROUP_NAME = "SG Lightfield"
GROUP_VERSION = 2  # 2: the local-warp glossy (sg_math.sg_glossy) in nested groups
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

    def __post_init__(self):
        if not self.tiles:
            self.tiles = [(kind, j) for j in range(self.sg_count) for kind in ("sg", "amp")]
            self.tiles += [("sh", j) for j in range(self.sh_count)]
            if self.has_irradiance:
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
                "has_irradiance": self.has_irradiance, "atlas_size": list(self.atlas_size),
                "tiles": [list(t) for t in self.tiles]}


SOCKET_TYPES = {"VALUE": "NodeSocketFloat", "VECTOR": "NodeSocketVector", "RGBA": "NodeSocketColor"}


def socket_type(value) -> str:
    """Interface socket type for a NodeOps value: an output socket, a Python number or a 3-tuple."""
    if isinstance(value, (int, float)):
        return "NodeSocketFloat"
    if isinstance(value, tuple):
        return "NodeSocketVector"
    return SOCKET_TYPES[value.type]


class NodeOps:
    """sg_shading operations as shader nodes. Constants stay Python numbers until an input needs them."""

    def __init__(self, tree, subgroups=None):
        self.tree = tree
        self.count = 0
        self.gate = None  # a non-negative colour later texture lookups are made to depend on
        self.subgroups = {} if subgroups is None else subgroups  # call name -> nested node group, built once

    def barrier(self, value):
        """Make later texture lookups depend on `value` (a sum that is >= 0) by adding min(value, 0) = 0 to their
        UVs. Cycles' SVM compiler otherwise schedules every lookup of the graph first and runs out of its
        255-slot stack (measured: "out of SVM stack space" and black materials at N = 8 with IWEV)."""
        self.gate = None if isinstance(value, tuple) else value

    def _node(self, kind, **props):
        node = self.tree.nodes.new(kind)
        for key, value in props.items():
            setattr(node, key, value)
        node.location = (200 * (self.count // COLUMN_NODES), -120 * (self.count % COLUMN_NODES))
        node.hide = True
        self.count += 1
        return node

    def call(self, name, function, **inputs):
        """function(ops, **inputs) -> {output: value} as one Group node. The nested group `<tree name> / name` is
        built on the first call and instanced after that: each node and link bpy adds costs time that grows with the
        tree's size, so one flat group takes time quadratic in its size (measured: 0.4 s for 500 Math nodes, 18 s
        for 2000), while the renderers flatten nested groups back into the same graph."""
        if name not in self.subgroups:
            self.subgroups[name] = self._build_subgroup(f"{self.tree.name} / {name}", function, inputs)
        node = self._node("ShaderNodeGroup", node_tree=self.subgroups[name])
        for key, value in inputs.items():
            self._feed(node.inputs[key], value)
        return {socket.name: socket for socket in node.outputs}

    def _build_subgroup(self, name, function, inputs):
        group = new_or_cleared_group(name)
        for key, value in inputs.items():
            group.interface.new_socket(key, in_out="INPUT", socket_type=socket_type(value))
        ops = NodeOps(group, self.subgroups)
        group_inputs = ops._node("NodeGroupInput")
        outputs = function(ops, **{key: group_inputs.outputs[key] for key in inputs})
        for key, value in outputs.items():
            group.interface.new_socket(key, in_out="OUTPUT", socket_type=socket_type(value))
        group_outputs = ops._node("NodeGroupOutput")
        for key, value in outputs.items():
            ops._feed(group_outputs.inputs[key], value)
        group[VERSION_KEY] = GROUP_VERSION
        return group

    def _feed(self, socket, value):
        if hasattr(value, "links") or hasattr(value, "is_linked"):
            self.tree.links.new(value, socket)
        else:
            socket.default_value = value

    def _math(self, operation, *values):
        node = self._node("ShaderNodeMath", operation=operation)
        for socket, value in zip(node.inputs, values):
            self._feed(socket, value)
        return node.outputs[0]

    def _vmath(self, operation, *values, output=0, scale=None):
        node = self._node("ShaderNodeVectorMath", operation=operation)
        for socket, value in zip(node.inputs, values):
            self._feed(socket, value)
        if scale is not None:
            self._feed(node.inputs["Scale"], scale)
        return node.outputs[output]

    def const(self, value):
        return float(value)

    def vconst(self, value):
        return tuple(float(v) for v in value)

    def add(self, a, b):
        return self._math("ADD", a, b)

    def sub(self, a, b):
        return self._math("SUBTRACT", a, b)

    def mul(self, a, b):
        return self._math("MULTIPLY", a, b)

    def div(self, a, b):
        return self._math("DIVIDE", a, b)

    def maximum(self, a, b):
        return self._math("MAXIMUM", a, b)

    def minimum(self, a, b):
        return self._math("MINIMUM", a, b)

    def clamp(self, a, lo, hi):
        node = self._node("ShaderNodeClamp", clamp_type="MINMAX")
        self._feed(node.inputs["Value"], a)
        self._feed(node.inputs["Min"], float(lo))
        self._feed(node.inputs["Max"], float(hi))
        return node.outputs[0]

    def exp(self, a):
        return self._math("EXPONENT", a)

    def sqrt(self, a):
        return self._math("SQRT", a)

    def sin(self, a):
        return self._math("SINE", a)

    def acos(self, a):
        return self._math("ARCCOSINE", a)

    def power(self, a, exponent):
        return self._math("POWER", a, float(exponent))

    def dot(self, a, b):
        return self._vmath("DOT_PRODUCT", a, b, output="Value")

    def cross(self, a, b):
        return self._vmath("CROSS_PRODUCT", a, b)

    def normalize(self, a):
        return self._vmath("NORMALIZE", a)

    def vadd(self, a, b):
        return self._vmath("ADD", a, b)

    def vsub(self, a, b):
        return self._vmath("SUBTRACT", a, b)

    def vmul(self, a, b):
        return self._vmath("MULTIPLY", a, b)

    def vscale(self, a, s):
        return self._vmath("SCALE", a, scale=s)

    def vmax(self, a, b):
        return self._vmath("MAXIMUM", a, b)

    def vmin(self, a, b):
        return self._vmath("MINIMUM", a, b)


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


def build_node_group(image, layout: SGTextureLayout, env_sgs=(), name: str = GROUP_NAME):
    """Create or update the node group and its nested groups (`<name> / ...`); returns it. `image` is the packed SG
    image (Non-Color, half float)."""
    group = new_or_cleared_group(name)
    sockets = [("UV", "INPUT", "NodeSocketVector"), ("Normal", "INPUT", "NodeSocketVector"),
               ("Roughness", "INPUT", "NodeSocketFloat"), ("F0", "INPUT", "NodeSocketColor"),
               ("Albedo", "INPUT", "NodeSocketColor"), ("Total", "OUTPUT", "NodeSocketColor"),
               ("Glossy", "OUTPUT", "NodeSocketColor"), ("Diffuse", "OUTPUT", "NodeSocketColor"),
               ("Environment", "OUTPUT", "NodeSocketColor")]
    for socket_name, in_out, socket_type in sockets:
        group.interface.new_socket(socket_name, in_out=in_out, socket_type=socket_type)
    ops = NodeOps(group)
    inputs = ops._node("NodeGroupInput")
    geometry = ops._node("ShaderNodeNewGeometry")
    columns, rows = layout.grid
    width, height = (float(v) for v in layout.atlas_size)
    # Shared by every tile: the four texel centres around UV (clamped inside the atlas) and their weights.
    texel = ops._vmath("SUBTRACT", ops._vmath("MULTIPLY", inputs.outputs["UV"], (width, height, 1.0)), (0.5, 0.5, 0.0))
    base = ops._vmath("FLOOR", texel)
    fraction = ops._node("ShaderNodeSeparateXYZ")
    group.links.new(ops._vmath("SUBTRACT", texel, base), fraction.inputs[0])
    tx, ty = fraction.outputs["X"], fraction.outputs["Y"]
    corners = []
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        corner = ops._vmath("MULTIPLY", ops._vmath("ADD", base, (dx + 0.5, dy + 0.5, 0.0)),
                            (1.0 / width, 1.0 / height, 1.0))
        corner = ops._vmath("MAXIMUM", ops._vmath("MINIMUM", corner, (1 - 0.5 / width, 1 - 0.5 / height, 1.0)),
                            (0.5 / width, 0.5 / height, 0.0))
        wx = tx if dx else ops.sub(1.0, tx)
        wy = ty if dy else ops.sub(1.0, ty)
        corners.append((corner, ops.mul(wx, wy)))
    cache = {}
    corner_inputs = {f"corner {i}": corner for i, (corner, _) in enumerate(corners)}
    corner_inputs.update({f"weight {i}": weight for i, (_, weight) in enumerate(corners)})

    def bilinear_tile(tile_ops, offset, **corner_sockets):
        """The four 'Closest' lookups of the tile at `offset` (column, row), blended: {'colour', 'alpha'}."""
        color_sum = alpha_sum = None
        for i in range(len(corners)):
            shifted = tile_ops._vmath("ADD", corner_sockets[f"corner {i}"], offset)
            uv = tile_ops._vmath("MULTIPLY", shifted, (1.0 / columns, 1.0 / rows, 1.0))
            texture = tile_ops._node("ShaderNodeTexImage", image=image, interpolation="Closest", extension="EXTEND")
            tile_ops.tree.links.new(uv, texture.inputs["Vector"])
            weight = corner_sockets[f"weight {i}"]
            color = tile_ops.vscale(texture.outputs["Color"], weight)
            alpha = tile_ops.mul(texture.outputs["Alpha"], weight)
            color_sum = color if color_sum is None else tile_ops.vadd(color_sum, color)
            alpha_sum = alpha if alpha_sum is None else tile_ops.add(alpha_sum, alpha)
        return {"colour": color_sum, "alpha": alpha_sum}

    def lookup(kind, j):
        if (kind, j) not in cache:
            col, row = layout.tile_offset(kind, j)
            offset = (float(col), float(row), 0.0)
            if ops.gate is not None:  # exactly (col, row, 0), but only once the previous SG is done
                offset = ops._vmath("ADD", ops._vmath("MINIMUM", ops.gate, (0.0, 0.0, 0.0)), offset)
            tile = ops.call("bilinear tile", bilinear_tile, offset=offset, **corner_inputs)
            cache[(kind, j)] = (tile["colour"], tile["alpha"])
        return cache[(kind, j)]

    result = shade(ops, lookup, inputs.outputs["Normal"], geometry.outputs["Incoming"], inputs.outputs["Roughness"],
                   inputs.outputs["F0"], inputs.outputs["Albedo"], layout.sg_count, layout.iwev_count,
                   [tuple(e) for e in env_sgs], layout.has_irradiance, layout.sh_count)
    outputs = ops._node("NodeGroupOutput")
    outputs.location = (200 * (ops.count // COLUMN_NODES + 1), 0)
    for key, socket_name in (("total", "Total"), ("glossy", "Glossy"), ("diffuse", "Diffuse"),
                             ("environment", "Environment")):
        ops._feed(outputs.inputs[socket_name], result[key] if not isinstance(result[key], tuple)
                  else (*result[key], 1.0))
    group[VERSION_KEY] = GROUP_VERSION
    group["sglf_layout"] = str(layout.to_dict())
    return group
