"""Stochastic-transparency strand renderer (Paper II §3.2), pure numpy so it runs inside Blender without torch.

This is the renderer whose output the hair filter sees, both when the training data is made and when the
"Filter Hair" operator runs, so the network never meets an input it was not trained on.

- Strands are Catmull-Rom curves (Blender's hair curve type), subdivided into polylines and drawn as
  1-pixel lines: one fragment per strand per pixel crossed.
- A fragment's alpha is fibre opacity x the strand's area inside the pixel over the pixel's area
  (width x length of the strand in that pixel: the paper's area factor baked into the alpha).
- Each of S samples per pixel keeps the nearest fragment that survives a hashed alpha test
  (Wyman & McGuire 2017): the random number hashes the strand id, the sample index and the fragment's
  model-space position quantised to the pixel footprint, so it is stable while camera and hair move.
- Light visibility comes from stochastic shadow maps (Enderton et al. 2011) along a directional light: in each
  1-sample map a fragment is lit when nothing that survived the light's hashed alpha test lies in front of it,
  and its lit fraction is the mean over a few maps with independent hashes (8 by default, one rasterisation).
  A single map freezes one random shadow pattern into every pixel sample, which no number of samples averages
  out and the filter cannot tell from strand detail: on 5 validation views 8 maps lower unfiltered 4-spp FLIP
  against Cycles from 0.134 to 0.116 (docs/design-additions.md §9).
- Shading is Scheuermann's (Paper II Fig. 3): colour factor = (F_d + F_TRT) V + ambient and
  highlight = F_R V, with F_d = sin(T, L) and F_R, F_TRT = max(0, sin(angle(T, H) + shift))^p. The print
  takes the specular angle between T and L, which would make highlights independent of the view; we use
  the half vector H of light and view, as Scheuermann does.

Per-sample features (Paper II §3.3.1): colour factor, highlight, alpha, depth, view-space tangent x, y.
Empty samples are all zero; depth is 1 at the nearest strand point and 0 at the farthest (reverse depth).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

FEATURE_NAMES = ("color_factor", "highlight", "alpha", "depth", "tangent_x", "tangent_y")
OUTPUT_NAMES = ("color_factor", "highlight", "alpha")
SHADOW_MAPS = 8  # stochastic shadow maps averaged per frame (see the module docstring)
# What the bench and the filters' validation composite with: hair colour, key light, grey background.
EVALUATION_LOOK = ((0.32, 0.17, 0.08), 3.0, 0.18)


@dataclass(frozen=True)
class HairShading:
    """Scheuermann's phenomenological hair model with Marschner-range shifts (degrees)."""
    opacity: float = 0.7  # one fibre's opacity
    ambient: float = 0.08
    shift_r_deg: float = -7.0
    shift_trt_deg: float = 10.5
    exponent_r: float = 250.0
    exponent_trt: float = 80.0


@dataclass
class Strands:
    """Hair curves: control points in world and model space, radius per point, curve offsets (C + 1)."""
    world: np.ndarray
    model: np.ndarray
    radius: np.ndarray
    offsets: np.ndarray
    groom: np.ndarray | None = None  # per curve: which hair object it came from (colours differ per object)

    def __post_init__(self):
        if self.groom is None:
            self.groom = np.zeros(len(self.offsets) - 1, np.int64)
        self.groom = np.asarray(self.groom, np.int64).reshape(-1)
        self.world = np.asarray(self.world, np.float64).reshape(-1, 3)
        self.model = np.asarray(self.model, np.float64).reshape(-1, 3)
        self.radius = np.asarray(self.radius, np.float64).reshape(-1)
        self.offsets = np.asarray(self.offsets, np.int64).reshape(-1)

    @property
    def curve_count(self) -> int:
        return len(self.offsets) - 1

    def curve_ids(self) -> np.ndarray:
        return np.repeat(np.arange(self.curve_count), np.diff(self.offsets))

    def bounds(self):
        return self.world.min(axis=0), self.world.max(axis=0)


@dataclass(frozen=True)
class PinholeCamera:
    """world_to_camera: 4x4 with the camera looking down -z (Blender's convention); focal length in pixels."""
    world_to_camera: np.ndarray
    focal_px: float
    width: int
    height: int
    shift_px: tuple = (0.0, 0.0)

    def project(self, points):
        """(x, y) in pixels with y = 0 at the top row, and view depth (> 0 in front)."""
        m = np.asarray(self.world_to_camera, np.float64)
        p = points @ m[:3, :3].T + m[:3, 3]
        depth = -p[:, 2]
        safe = np.where(depth > 1e-9, depth, 1e-9)
        x = self.width / 2 + self.shift_px[0] + self.focal_px * p[:, 0] / safe
        y = self.height / 2 - self.shift_px[1] - self.focal_px * p[:, 1] / safe
        return x, y, depth

    @property
    def position(self) -> np.ndarray:
        m = np.asarray(self.world_to_camera, np.float64)
        return -m[:3, :3].T @ m[:3, 3]

    def to_view(self, vectors):
        return vectors @ np.asarray(self.world_to_camera, np.float64)[:3, :3].T


def look_at(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """world_to_camera for a camera at eye looking at target (Blender camera axes)."""
    eye, target, up = (np.asarray(v, np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    if np.linalg.norm(right) < 1e-8:
        right = np.cross((0.0, 1.0, 0.0), back)
    right /= np.linalg.norm(right)
    true_up = np.cross(back, right)
    rotation = np.stack([right, true_up, back])
    m = np.eye(4)
    m[:3, :3] = rotation
    m[:3, 3] = -rotation @ eye
    return m


def random_camera(rng: np.random.Generator, low, high, size: int) -> PinholeCamera:
    """A camera 0.35-0.9 m from the groom's box (low, high), looking at a random point of it and seeing
    5-45 cm across (log-uniform): from whole-head views to close-ups where strands are a pixel wide."""
    low, high = np.asarray(low, np.float64), np.asarray(high, np.float64)
    centre = (low + high) / 2
    target = centre + (rng.random(3) - 0.5) * (high - low) * 0.6
    azimuth = rng.uniform(0, 2 * np.pi)
    elevation = np.radians(rng.uniform(-15, 60))
    distance = float(np.linalg.norm(high - low)) / 2 + rng.uniform(0.25, 0.7)
    eye = target + distance * np.array([np.cos(elevation) * np.cos(azimuth),
                                        np.cos(elevation) * np.sin(azimuth), np.sin(elevation)])
    view_width = float(np.exp(rng.uniform(np.log(0.05), np.log(0.45))))
    return PinholeCamera(look_at(eye, target), size * distance / view_width, size, size)


def random_light(rng: np.random.Generator) -> np.ndarray:
    """A direction to the light, uniform on the sphere."""
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def random_view(rng: np.random.Generator, strands: Strands, size: int, samples: int, tries: int = 16, **render_options):
    """random_camera and random_light, drawn again while no strand crosses a pixel (a close-up aimed between
    strands): such a view teaches the filter nothing and has no score. The first draw is random_camera's
    and random_light's, so views that show hair are the ones earlier datasets have.
    Returns (camera, light, render, draws); ValueError when no draw in `tries` shows any hair."""
    for draw in range(1, tries + 1):
        camera = random_camera(rng, *strands.bounds(), size)
        light = random_light(rng)
        render = render_stochastic(strands, camera, light, samples, **render_options)
        if render.fragment_count:
            return camera, light, render, draw
    raise ValueError(f"none of {tries} random views of the groom shows any hair")


def subdivide_catmull_rom(strands: Strands, segments_per_span: int = 4) -> Strands:
    """Uniform Catmull-Rom through the control points (end points repeated), as Blender evaluates hair."""
    counts = np.diff(strands.offsets)
    starts = np.repeat(strands.offsets[:-1], counts)
    ends = np.repeat(strands.offsets[1:] - 1, counts)
    index = np.arange(len(strands.world))
    span = index[index < ends]  # first point of each span
    if span.size == 0:
        return strands
    i0 = np.maximum(span - 1, starts[span])
    i3 = np.minimum(span + 2, ends[span])
    t = np.arange(segments_per_span) / segments_per_span
    t2, t3 = t * t, t * t * t
    weights = 0.5 * np.stack([-t3 + 2 * t2 - t, 3 * t3 - 5 * t2 + 2, -3 * t3 + 4 * t2 + t, t3 - t2], axis=1)

    def spline(values):
        v = values.reshape(len(values), -1)
        out = np.einsum("kw,swc->skc", weights, np.stack([v[i0], v[span], v[span + 1], v[i3]], axis=1))
        return out

    def linear(values):
        return values[span, None] * (1 - t) + values[span + 1, None] * t

    # Each curve: its spans' samples, then its last control point.
    last = strands.offsets[1:] - 1
    spans_per_curve = np.maximum(counts - 1, 0)
    new_counts = spans_per_curve * segments_per_span + (counts > 0)
    new_offsets = np.concatenate([[0], np.cumsum(new_counts)])
    order_key = np.concatenate([np.repeat(span, segments_per_span) * segments_per_span + np.tile(
        np.arange(segments_per_span), len(span)), last * segments_per_span])
    order = np.argsort(order_key, kind="stable")

    def assemble(span_values, end_values):
        flat = np.concatenate([span_values.reshape(len(span) * segments_per_span, -1),
                               end_values.reshape(len(last), -1)])
        return flat[order]

    return Strands(assemble(spline(strands.world), strands.world[last]),
                   assemble(spline(strands.model), strands.model[last]),
                   assemble(linear(strands.radius), strands.radius[last]).reshape(-1),
                   new_offsets, strands.groom)


def hash_uniform(*keys: np.ndarray) -> np.ndarray:
    """Uniform [0, 1) from integer keys (64-bit splitmix finaliser, chained)."""
    with np.errstate(over="ignore"):
        h = np.full(np.broadcast(*keys).shape, 0x9E3779B97F4A7C15, np.uint64)
        for key in keys:
            h = h ^ (np.asarray(key).astype(np.int64).astype(np.uint64) + np.uint64(0x9E3779B97F4A7C15)
                     + (h << np.uint64(6)) + (h >> np.uint64(2)))
            h = (h ^ (h >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
            h = (h ^ (h >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
            h = h ^ (h >> np.uint64(31))
    return (h >> np.uint64(11)).astype(np.float64) / float(1 << 53)


def hashed_alpha_random(curve, model_position, footprint, sample_index) -> np.ndarray:
    """Wyman & McGuire: quantise the model-space position at the (power-of-two) pixel footprint."""
    cell = np.exp2(np.floor(np.log2(np.maximum(footprint, 1e-12))))
    q = np.floor(model_position / cell[:, None]).astype(np.int64)
    level = np.log2(cell).astype(np.int64)
    return hash_uniform(curve, q[:, 0], q[:, 1], q[:, 2], level, np.full(len(curve), sample_index))


@dataclass
class Fragments:
    """One per strand per pixel crossed (sorted by nothing in particular)."""
    pixel: np.ndarray  # flat index into the image
    depth: np.ndarray
    world: np.ndarray
    model: np.ndarray
    tangent: np.ndarray  # unit, world space, root to tip
    radius: np.ndarray
    curve: np.ndarray
    length: np.ndarray  # of the strand inside the pixel, in pixels

    def coverage(self, opacity: float, pixel_size) -> np.ndarray:
        """Alpha: fibre opacity x the strand's area inside the pixel (width x length) over the pixel's area."""
        return opacity * np.minimum(1.0, 2 * self.radius / pixel_size * self.length)


def rasterize_lines(strands: Strands, x, y, depth, width: int, height: int) -> Fragments:
    """1-pixel lines through projected polylines: samples every half pixel, one fragment per (curve, pixel)."""
    curve_of_point = strands.curve_ids()
    seg = np.flatnonzero(curve_of_point[:-1] == curve_of_point[1:]) if len(curve_of_point) > 1 else np.zeros(0, int)
    a, b = seg, seg + 1
    ok = (depth[a] > 1e-6) & (depth[b] > 1e-6)
    a, b = a[ok], b[ok]
    length = np.hypot(x[b] - x[a], y[b] - y[a])
    steps = np.minimum(np.ceil(length * 2).astype(np.int64), 4 * (width + height)) + 1
    seg_of_sample = np.repeat(np.arange(len(a)), steps)
    first = np.concatenate([[0], np.cumsum(steps)[:-1]])
    t = (np.arange(len(seg_of_sample)) - first[seg_of_sample] + 0.5) / steps[seg_of_sample]
    sa, sb = a[seg_of_sample], b[seg_of_sample]
    px = x[sa] + (x[sb] - x[sa]) * t
    py = y[sa] + (y[sb] - y[sa]) * t
    inside = (px >= 0) & (px < width) & (py >= 0) & (py < height)
    sa, sb, t, px, py = sa[inside], sb[inside], t[inside], px[inside], py[inside]
    spacing = (length / steps)[seg_of_sample[inside]]
    pixel = np.floor(py).astype(np.int64) * width + np.floor(px).astype(np.int64)
    curve = curve_of_point[sa]
    _, keep, group = np.unique(curve * (width * height) + pixel, return_index=True, return_inverse=True)
    group = group.reshape(-1)
    length_in_pixel = np.bincount(group, weights=spacing, minlength=len(keep))
    # Mean radius along the piece of strand in the pixel (strands taper: one end's radius would be biased).
    sample_radius = strands.radius[sa] + (strands.radius[sb] - strands.radius[sa]) * t
    mean_radius = np.bincount(group, weights=spacing * sample_radius, minlength=len(keep)) / np.maximum(
        length_in_pixel, 1e-12)
    sa, sb, t, pixel, curve = sa[keep], sb[keep], t[keep], pixel[keep], curve[keep]
    # Perspective-correct position: interpolate in screen space, then undo the projection's 1/z.
    inv = (1 - t) / depth[sa] + t / depth[sb]
    tw = (t / depth[sb]) / inv
    lerp = lambda v: v[sa] + (v[sb] - v[sa]) * tw[:, None]  # noqa: E731
    direction = strands.world[sb] - strands.world[sa]
    direction /= np.maximum(np.linalg.norm(direction, axis=1, keepdims=True), 1e-12)
    return Fragments(pixel, 1.0 / inv, lerp(strands.world), lerp(strands.model), direction, mean_radius, curve,
                     length_in_pixel)


def strand_lobes(tangent, to_light, to_viewer, shading: HairShading):
    """(colour factor without ambient, highlight) of Paper II Fig. 3 with the half-vector specular angle."""
    cos_tl = np.clip(np.sum(tangent * to_light, axis=-1), -1, 1)
    diffuse = np.sqrt(1 - cos_tl ** 2)
    half = to_light + to_viewer
    half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    angle_th = np.arccos(np.clip(np.sum(tangent * half, axis=-1), -1, 1))
    r = np.maximum(np.sin(angle_th + np.radians(shading.shift_r_deg)), 0) ** shading.exponent_r
    trt = np.maximum(np.sin(angle_th + np.radians(shading.shift_trt_deg)), 0) ** shading.exponent_trt
    return diffuse + trt, r


def _nearest_per_pixel(pixel, depth):
    """Indices of the nearest entry per distinct pixel."""
    if pixel.size == 0:
        return pixel
    order = np.lexsort((depth, pixel))
    first = np.ones(len(order), bool)
    first[1:] = pixel[order][1:] != pixel[order][:-1]
    return order[first]


@dataclass(frozen=True)
class ShadowMap:
    """M 1-sample stochastic shadow maps along a directional light (orthographic), sharing one rasterisation."""
    to_light: np.ndarray
    basis: np.ndarray  # rows: u, v, toward light
    origin: np.ndarray  # (u, v) of texel (0, 0)
    texel: float
    size: int
    nearest: np.ndarray  # (M, size * size) light-space distance of the nearest surviving fragment, +inf if none

    def lit(self, world, bias) -> np.ndarray:
        """Fraction of the maps in which each point is lit (0 or 1 with one map)."""
        coords = world @ self.basis.T
        u = np.floor((coords[:, 0] - self.origin[0]) / self.texel).astype(np.int64)
        v = np.floor((coords[:, 1] - self.origin[1]) / self.texel).astype(np.int64)
        inside = (u >= 0) & (u < self.size) & (v >= 0) & (v < self.size)
        distance = -coords[:, 2]
        texel = v[inside] * self.size + u[inside]
        lit = np.zeros(len(world))
        for nearest in np.atleast_2d(self.nearest):  # one map at a time: memory stays O(points)
            blocker = np.full(len(world), np.inf)
            blocker[inside] = nearest[texel]
            lit += distance <= blocker + bias
        return lit / len(np.atleast_2d(self.nearest))


def stochastic_shadow_map(strands: Strands, to_light, shading: HairShading, size: int = 1024,
                          seed: int = 1_000_003, maps: int = 1) -> ShadowMap:
    if maps < 1:
        raise ValueError(f"a shadow estimate needs at least one map, got {maps}")
    to_light = np.asarray(to_light, np.float64) / np.linalg.norm(to_light)
    helper = (0.0, 0.0, 1.0) if abs(to_light[2]) < 0.9 else (1.0, 0.0, 0.0)
    u_axis = np.cross(helper, to_light)
    u_axis /= np.linalg.norm(u_axis)
    v_axis = np.cross(to_light, u_axis)
    basis = np.stack([u_axis, v_axis, to_light])
    coords = strands.world @ basis.T
    low, high = coords[:, :2].min(axis=0), coords[:, :2].max(axis=0)
    texel = float(max(high - low) * (1 + 2 / size) / size) or 1e-6
    origin = low - texel
    x = (coords[:, 0] - origin[0]) / texel
    y = (coords[:, 1] - origin[1]) / texel
    fragments = rasterize_lines(strands, x, y, np.ones(len(x)), size, size)
    distance = -(fragments.world @ to_light)
    alpha = fragments.coverage(shading.opacity, texel)
    order = np.lexsort((distance, fragments.pixel))  # per texel, nearest first
    pixel, distance, alpha = fragments.pixel[order], distance[order], alpha[order]
    curve, model, footprint = fragments.curve[order], fragments.model[order], np.full(len(alpha), texel)
    nearest = np.full((maps, size * size), np.inf)
    for m in range(maps):
        survivors = np.flatnonzero(hashed_alpha_random(curve, model, footprint, seed + m) < alpha)
        first = np.ones(len(survivors), bool)
        first[1:] = pixel[survivors[1:]] != pixel[survivors[:-1]]
        nearest[m, pixel[survivors[first]]] = distance[survivors[first]]
    return ShadowMap(to_light, basis, origin, texel, size, nearest)


@dataclass
class StochasticRender:
    """Per-sample features (S, 6, H, W), and what the renderer used (for compositing and diagnostics)."""
    features: np.ndarray
    fragment_count: int
    depth_range: tuple
    extras: dict = field(default_factory=dict)

    @property
    def samples(self) -> int:
        return self.features.shape[0]

    def network_input(self, samples: int | None = None) -> np.ndarray:
        """(1, 6*S, H, W) float32 in the order the U-Net expects: sample-major, features inside."""
        s = self.samples if samples is None else samples
        if s > self.samples:
            raise ValueError(f"the render holds {self.samples} samples per pixel, the network needs {s}")
        f = self.features[:s]
        return f.reshape(1, s * f.shape[1], f.shape[2], f.shape[3]).astype(np.float32)

    def unfiltered(self, samples: int | None = None) -> np.ndarray:
        """Plain stochastic transparency: (3, H, W) colour factor, highlight (straight) and alpha."""
        f = self.features[: self.samples if samples is None else samples]
        covered = (f[:, 2] > 0).astype(np.float64)
        alpha = covered.mean(axis=0)
        safe = np.where(alpha > 0, alpha, 1.0)
        color = np.where(alpha > 0, (f[:, 0] * covered).mean(axis=0) / safe, 1.0)
        highlight = np.where(alpha > 0, (f[:, 1] * covered).mean(axis=0) / safe, 0.0)
        return np.stack([color, highlight, alpha])


def render_stochastic(strands: Strands, camera: PinholeCamera, to_light, samples: int,
                      shading: HairShading = HairShading(), shadow_map_size: int = 1024,
                      opaque_depth_at=None, subdivisions: int = 4,
                      sample_offset: int = 0, shadow_maps: int = SHADOW_MAPS) -> StochasticRender:
    """Render S stochastic-transparency samples per pixel of the strands' features.

    opaque_depth_at: optional function (flat pixel indices) -> (H*W,) view depth of opaque geometry there (asked
    only for the pixels strands cross); strand fragments behind it are dropped.
    sample_offset: first hash sample index (disjoint offsets give independent renders of the same frame).
    """
    fine = subdivide_catmull_rom(strands, subdivisions) if subdivisions > 1 else strands
    to_light = np.asarray(to_light, np.float64) / np.linalg.norm(to_light)
    width, height = camera.width, camera.height
    x, y, depth = camera.project(fine.world)
    fragments = rasterize_lines(fine, x, y, depth, width, height)
    if opaque_depth_at is not None:
        visible = fragments.depth < np.asarray(opaque_depth_at(np.unique(fragments.pixel)), np.float64)[fragments.pixel]
        fragments = Fragments(*(getattr(fragments, name)[visible] for name in Fragments.__dataclass_fields__))
    footprint = fragments.depth / camera.focal_px
    alpha = fragments.coverage(shading.opacity, footprint)
    shadow = stochastic_shadow_map(fine, to_light, shading, shadow_map_size, maps=shadow_maps)
    lit = shadow.lit(fragments.world, bias=2 * shadow.texel + 2 * fragments.radius)
    to_viewer = camera.position - fragments.world
    to_viewer /= np.maximum(np.linalg.norm(to_viewer, axis=1, keepdims=True), 1e-12)
    color, highlight = strand_lobes(fragments.tangent, to_light, to_viewer, shading)
    color = color * lit + shading.ambient
    highlight = highlight * lit
    view_tangent = camera.to_view(fragments.tangent)
    view_tangent /= np.maximum(np.linalg.norm(view_tangent, axis=1, keepdims=True), 1e-12)
    _, _, point_depth = camera.project(fine.world)
    near, far = float(point_depth.min()), float(point_depth.max())
    reverse_depth = 1 - (fragments.depth - near) / max(far - near, 1e-9)
    per_fragment = np.stack([color, highlight, alpha, np.clip(reverse_depth, 0, 1),
                             view_tangent[:, 0], view_tangent[:, 1]], axis=1)
    features = np.zeros((samples, len(FEATURE_NAMES), height * width), np.float32)
    groom = np.full((samples, height * width), -1, np.int16)
    for s in range(samples):
        survive = hashed_alpha_random(fragments.curve, fragments.model, footprint, sample_offset + s) < alpha
        index = np.flatnonzero(survive)
        chosen = index[_nearest_per_pixel(fragments.pixel[index], fragments.depth[index])]
        features[s][:, fragments.pixel[chosen]] = per_fragment[chosen].T
        groom[s, fragments.pixel[chosen]] = fine.groom[fragments.curve[chosen]]
    footprint = np.zeros(height * width, bool)
    footprint[fragments.pixel] = True  # every pixel a strand crosses, before the alpha test
    return StochasticRender(features.reshape(samples, len(FEATURE_NAMES), height, width), len(fragments.pixel),
                            (near, far), {"lit_fraction": float(lit.mean()) if lit.size else 1.0,
                                          "groom": groom.reshape(samples, height, width),
                                          "footprint": footprint.reshape(height, width)})


def hair_color_map(groom_samples: np.ndarray, colors: np.ndarray) -> np.ndarray:
    """(H, W, 3) hair colour per pixel from the grooms the samples hit (Paper II's network knows one colour;
    with several differently coloured grooms each pixel takes the mean colour of its samples' grooms, and
    uncovered pixels the first groom's colour)."""
    colors = np.asarray(colors, np.float64).reshape(-1, 3)
    covered = groom_samples >= 0
    picked = colors[np.maximum(groom_samples, 0)] * covered[..., None]
    count = covered.sum(axis=0)[..., None]
    return np.where(count > 0, picked.sum(axis=0) / np.maximum(count, 1), colors[0])


def composite(outputs: np.ndarray, hair_color, background: np.ndarray, light=1.0) -> np.ndarray:
    """(3, H, W) colour factor, highlight, alpha -> (H, W, 3) image over background (H, W, 3), linear.
    hair_color: (3,) or a per-pixel (H, W, 3) map; light: the key light's irradiance colour."""
    color_factor, highlight, alpha = outputs[0], outputs[1], np.clip(outputs[2], 0, 1)
    hair = np.asarray(light, np.float64) * (color_factor[..., None] * np.asarray(hair_color, np.float64)
                                            + highlight[..., None])
    return alpha[..., None] * hair + (1 - alpha[..., None]) * np.asarray(background, np.float64)
