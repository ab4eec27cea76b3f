"""The environment's global SGs: a compact bright source survives the fit where and as bright as it is, and a glossy
floor's reflection of it keeps its light (numpy shading against quadrature of the map)."""
import math

import numpy as np

from sg_lightfield.bake_directory.image_metrics import LUMINANCE
from sg_lightfield.shaders.octahedral import (downsample_octahedral, oct_decode, pixel_centers_uv, pixel_directions,
                                              pixel_solid_angles)
from sg_lightfield.shaders.sg_math import ggx_brdf_cos
from sg_lightfield.shaders.sg_shading import NumpyOps, glossy_sg, pixel_terms
from sg_lightfield.training.env_fit import compact_sources, fit_environment

LAMP = np.array([-0.83, 0.25, 0.5]) / np.linalg.norm([-0.83, 0.25, 0.5])
LAMP_RADIUS = math.radians(2.0)
LAMP_RADIANCE = np.array([300.0, 220.0, 120.0])


def _room(directions):
    """A dim room: brighter above than below, plus a lamp 2 degrees in radius (a third of the power)."""
    z = directions[..., 2:3]
    sky = 0.25 + 0.5 * np.clip(z, 0, 1) * np.array([0.9, 1.0, 1.1])
    lamp = (directions @ LAMP > math.cos(LAMP_RADIUS))[..., None] * LAMP_RADIANCE
    return sky + lamp


def _box_filtered_map(resolution, sub=8):
    """What the light-field camera renders with its box filter: each pixel's mean over a sub x sub grid."""
    offsets = ((np.arange(sub) + 0.5) / sub - 0.5) * 2.0 / resolution
    centres = pixel_centers_uv(resolution)
    total = np.zeros((resolution, resolution, 3))
    for du in offsets:
        for dv in offsets:
            total += _room(oct_decode(centres + np.array([du, dv])))
    return total / sub**2


def test_a_compact_lamp_becomes_one_sg_where_it_is_with_its_power():
    radiance = _box_filtered_map(64)
    sources, rest = compact_sources(downsample_octahedral(radiance, 32))
    lamp_power = LAMP_RADIANCE * 2 * math.pi * (1 - math.cos(LAMP_RADIUS))
    axis, sharpness, amplitude = sources[0]
    assert math.degrees(math.acos(np.clip(axis @ LAMP, -1, 1))) < 1.5
    sg_power = amplitude * 2 * math.pi / sharpness
    assert np.allclose(sg_power, lamp_power, rtol=0.15), (sg_power, lamp_power)
    assert len(sources) == 1  # the smooth room is not a source
    assert rest.max() < 0.5 * LAMP_RADIANCE.min()  # what is left is the room


def test_a_glossy_floor_reflects_the_lamp_with_its_light():
    """Over floor points whose mirror directions sweep past the lamp, the SG shading of the fitted environment
    keeps the light of the quadrature of the map (a log-loss fit alone lost two thirds of it on such a lamp in
    demo:materials)."""
    radiance = _box_filtered_map(64)
    sgs = fit_environment(radiance, 16)
    fine = 256
    directions = pixel_directions(fine).reshape(-1, 3)
    solid = pixel_solid_angles(fine).reshape(-1)
    environment = _box_filtered_map(fine, sub=4).reshape(-1, 3)
    ops, normal = NumpyOps(), np.array([[0.0, 0.0, 1.0]])
    for roughness in (0.15, 0.3):
        truth, shaded = [], []
        for elevation in np.radians(np.linspace(20, 40, 5)):
            for azimuth_offset in np.radians(np.linspace(-8, 8, 5)):
                azimuth = math.atan2(LAMP[1], LAMP[0]) + math.pi + azimuth_offset
                view = np.array([[math.cos(azimuth) * math.cos(elevation), math.sin(azimuth) * math.cos(elevation),
                                  math.sin(elevation)]])
                f = ggx_brdf_cos(directions, view, normal, roughness, np.full((1, 3), 0.04))
                truth.append((f * environment * solid[:, None]).sum(0) @ LUMINANCE)
                terms = pixel_terms(ops, normal, view, np.array([roughness]))
                glossy = sum(glossy_sg(ops, **terms, f0=np.full((1, 3), 0.04), axis=np.asarray(a)[None],
                                       sharpness=np.array([s]), amplitude=np.asarray(m)[None])["glossy"]
                             for a, s, m in sgs)
                shaded.append(float(glossy[0] @ LUMINANCE))
        ratio = np.mean(shaded) / np.mean(truth)
        assert 0.8 < ratio < 1.25, (roughness, ratio)


def test_black_uniform_and_sun_like_environments_fit_to_finite_sgs():
    """The extremes: a black world, a uniform grey one (no sources in either), and a sun-like pixel 10^6 brighter
    than the sky (one source holding its power, finite everywhere)."""
    black = np.zeros((32, 32, 3))
    grey = np.full((32, 32, 3), 0.7)
    sun = np.full((32, 32, 3), 0.2)
    sun[20, 11] = 2e5
    assert compact_sources(black)[0] == [] and compact_sources(grey)[0] == []
    for radiance in (black, grey, sun):
        sgs = fit_environment(radiance, 16, steps=100)
        assert len(sgs) == 16
        assert all(np.isfinite(np.r_[a, s, m]).all() and s > 0 and (np.asarray(m) >= 0).all() for a, s, m in sgs)
    sources, _ = compact_sources(sun)
    sun_power = 2e5 * pixel_solid_angles(32)[20, 11]
    assert len(sources) == 1
    assert np.allclose(sources[0][2] * 2 * math.pi / sources[0][1], sun_power, rtol=0.1)
    assert sources[0][0] @ pixel_directions(32)[20, 11] > math.cos(math.radians(3))
