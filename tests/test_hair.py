"""The hair tool end to end: the numpy stochastic-transparency renderer, the Cycles reference it is trained
against, training pairs on disk, training with checkpoints and resume, the onnxruntime filter with its bad
inputs, and the Filter Hair operator and command line on the `hair` demo scene."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from sg_lightfield.hair import pairs as hair_pairs
from sg_lightfield.hair import raster as hr
from sg_lightfield.hair.filtering import (SHIPPED_MODEL, SHIPPED_MODELS, HairFilterError, load_filter, mean_as_composited,
                                 mirror_features, unmirror)

REPO = Path(__file__).resolve().parent.parent


def straight_strands(curves, radius=0.001):
    """curves: list of (start, end) world points; 4 control points each, model space = world."""
    points, offsets = [], [0]
    for start, end in curves:
        start, end = np.asarray(start, float), np.asarray(end, float)
        points += [start + (end - start) * t for t in np.linspace(0, 1, 4)]
        offsets.append(len(points))
    points = np.array(points)
    return hr.Strands(points, points, np.full(len(points), radius), np.array(offsets))


def front_camera(size=64, view_width=0.2):
    """Looking along +y from y = -1 at the origin, seeing view_width metres across."""
    return hr.PinholeCamera(hr.look_at((0, -1, 0), (0, 0, 0)), size / view_width, size, size)


# ------------------------------------------------------------------ numpy renderer

def test_catmull_rom_passes_through_the_control_points_and_keeps_curves_apart():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(9, 3))
    strands = hr.Strands(points, points, np.linspace(1, 2, 9), np.array([0, 5, 9]), np.array([0, 1]))
    fine = hr.subdivide_catmull_rom(strands, 4)
    assert list(fine.offsets) == [0, 17, 30]
    np.testing.assert_allclose(fine.world[0:17:4], points[0:5], atol=1e-12)
    np.testing.assert_allclose(fine.world[17::4], points[5:9], atol=1e-12)
    np.testing.assert_allclose(fine.radius[0:17:4], strands.radius[0:5])


def test_alpha_is_the_strand_area_in_the_pixel_at_any_angle():
    """Sum of per-pixel alpha = opacity x width x length / pixel area, whatever the strand's direction."""
    camera = front_camera(128, 0.2)
    pixel = 0.2 / 128
    for angle in np.radians([0, 17, 45, 80]):
        direction = np.array([np.cos(angle), 0, np.sin(angle)])
        strands = straight_strands([(-0.06 * direction, 0.06 * direction)], radius=0.2 * pixel)
        x, y, depth = camera.project(strands.world)
        fragments = hr.rasterize_lines(strands, x, y, depth, 128, 128)
        area = fragments.coverage(1.0, depth[0] / camera.focal_px).sum()
        expected = (0.12 / pixel) * 0.4  # length in pixels x width in pixels (the strand is 1 m away)
        assert abs(area / expected - 1) < 0.03, (np.degrees(angle), area, expected)


def test_stochastic_transparency_is_unbiased_and_hashing_is_stable():
    """Eight overlapping strands in front of each other: the mean coverage of many samples approaches
    1 - prod(1 - alpha_i); the same frame rendered twice gives the same samples."""
    curves = [((-0.08, 0.002 * k, -0.002 * k), (0.08, 0.002 * k, 0.002 * k)) for k in range(8)]
    strands = straight_strands(curves, radius=0.0006)
    camera = front_camera(64, 0.2)
    shading = hr.HairShading(opacity=0.7)
    render = hr.render_stochastic(strands, camera, (0, -1, 0), 64, shading=shading)
    again = hr.render_stochastic(strands, camera, (0, -1, 0), 4, shading=shading)
    np.testing.assert_array_equal(render.features[:4], again.features)
    fine = hr.subdivide_catmull_rom(strands)
    x, y, depth = camera.project(fine.world)
    fragments = hr.rasterize_lines(fine, x, y, depth, 64, 64)
    alpha = fragments.coverage(shading.opacity, fragments.depth / camera.focal_px)
    transmittance = np.ones(64 * 64)
    np.multiply.at(transmittance, fragments.pixel, 1 - alpha)
    expected = 1 - transmittance.reshape(64, 64)
    estimated = render.unfiltered()[2]
    hit = expected > 0.05
    assert abs(estimated[hit].mean() / expected[hit].mean() - 1) < 0.05
    assert abs(estimated.sum() / expected.sum() - 1) < 0.05


def test_stochastic_shadow_map_lets_through_one_minus_alpha():
    """A strand right behind another (seen from the light) is lit with probability 1 - alpha of the front one."""
    shading = hr.HairShading(opacity=0.6)
    front = [((-0.05, 0.0, 0.001 * k), (0.05, 0.0, 0.001 * k)) for k in range(40)]
    back = [((-0.05, 0.02, 0.001 * k), (0.05, 0.02, 0.001 * k)) for k in range(40)]
    strands = straight_strands(front + back, radius=0.002)
    shadow = hr.stochastic_shadow_map(strands, (0, -1, 0), shading, size=256)
    samples = np.stack([np.linspace(-0.04, 0.04, 400), np.full(400, 0.02), np.full(400, 0.02)], axis=1)
    lit = shadow.lit(samples, bias=0.004).mean()
    front_alpha = shading.opacity * min(1.0, 2 * 0.002 / shadow.texel)
    # Strands 1 mm apart and 4 mm wide: each shadow-map texel sees about four front strands.
    assert 0.0 <= lit < 1 - front_alpha + 0.1
    assert shadow.lit(samples * [1, 0, 1] - [0, 0.01, 0], bias=0.004).all()  # in front of everything: lit


def test_several_shadow_maps_average_independent_realisations():
    """M maps from one rasterisation are the M single maps of consecutive seeds averaged; their lit fraction
    approaches the transmittance as 1/sqrt(M) (here against 64 maps), where one map gives only 0 or 1."""
    shading = hr.HairShading(opacity=0.6)
    front = [((-0.05, 0.0, 0.0013 * k), (0.05, 0.0, 0.0013 * k)) for k in range(40)]
    back = [((-0.05, 0.02, 0.0013 * k), (0.05, 0.02, 0.0013 * k)) for k in range(40)]
    strands = straight_strands(front + back, radius=0.0003)
    points = np.stack([np.linspace(-0.04, 0.04, 2000), np.full(2000, 0.02), np.linspace(0.002, 0.048, 2000)],
                      axis=1)
    lit = {m: hr.stochastic_shadow_map(strands, (0, -1, 0), shading, size=256, maps=m).lit(points, bias=0.004)
           for m in (1, 4, 16, 64)}
    singles = [hr.stochastic_shadow_map(strands, (0, -1, 0), shading, size=256, seed=1_000_003 + m).lit(
        points, bias=0.004) for m in range(4)]
    np.testing.assert_array_equal(lit[4], np.mean(singles, axis=0))
    assert set(np.unique(lit[1])) <= {0.0, 1.0}
    assert 0.2 < lit[64].mean() < 0.9  # partly shadowed: the front strands let some light through
    spread = {m: np.sqrt(((lit[m] - lit[64]) ** 2).mean()) for m in (1, 4, 16)}
    assert spread[4] < 0.65 * spread[1] and spread[16] < 0.65 * spread[4], spread


def test_lobes_follow_the_shading_model():
    """F_d = sin(T, L); R and TRT peak where angle(T, H) + shift = 90 degrees (H = L = V here)."""
    shading = hr.HairShading()
    theta = np.radians(np.linspace(0, 180, 18001))
    tangents = np.stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)], axis=1)
    up = np.array([0.0, 0.0, 1.0])
    color, highlight = hr.strand_lobes(tangents, up, up, shading)
    trt = color - np.sin(theta)
    assert np.degrees(theta[np.argmax(highlight)]) == pytest.approx(90 - shading.shift_r_deg, abs=0.02)
    assert np.degrees(theta[np.argmax(trt)]) == pytest.approx(90 - shading.shift_trt_deg, abs=0.02)
    assert highlight.max() == pytest.approx(1.0) and trt.max() == pytest.approx(1.0)
    assert highlight[np.abs(np.degrees(theta) - 97) > 15].max() < 0.01  # exponent 250: a narrow lobe


def test_the_networks_unfiltered_estimate_is_the_renderers():
    """The blend configurations compute plain stochastic transparency inside the network (torch, exported to
    ONNX); it must be what the renderer's numpy `unfiltered` gives."""
    import torch

    from sg_lightfield.hair.unet import unfiltered_estimate

    curves = [((-0.08, 0.002 * k, -0.03 + 0.01 * k), (0.08, 0.002 * k, 0.03 - 0.01 * k)) for k in range(6)]
    render = hr.render_stochastic(straight_strands(curves, radius=0.0006), front_camera(64, 0.2), (0.3, -1, 0.4), 4)
    for samples in (1, 2, 4):
        expected = render.unfiltered(samples)
        assert 0 < expected[2].max() and (expected[2] == 0).any()
        got = unfiltered_estimate(torch.from_numpy(render.network_input(samples)))[0].double().numpy()
        np.testing.assert_allclose(got, expected, atol=1e-6)


def test_composite_and_colour_map():
    outputs = np.stack([np.full((2, 2), 1.5), np.full((2, 2), 0.25), np.array([[0, 1], [0.5, 1]])])
    background = np.full((2, 2, 3), 0.2)
    image = hr.composite(outputs, (0.4, 0.2, 0.1), background, light=2.0)
    np.testing.assert_allclose(image[0, 0], 0.2)
    np.testing.assert_allclose(image[0, 1], 2.0 * (1.5 * np.array([0.4, 0.2, 0.1]) + 0.25))
    grooms = np.array([[[0, 1], [-1, 1]], [[1, 1], [-1, 0]]])
    colors = np.array([[1.0, 0, 0], [0, 1.0, 0]])
    color_map = hr.hair_color_map(grooms, colors)
    np.testing.assert_allclose(color_map[0, 0], [0.5, 0.5, 0])
    np.testing.assert_allclose(color_map[1, 0], [1, 0, 0])  # no sample: the first groom's colour


# ------------------------------------------------------------------ pairs, training, filter

def test_pairs_round_trip_and_split(tmp_path):
    rng = np.random.default_rng(1)
    features = rng.random((4, 6, 16, 24)).astype(np.float32)
    target = rng.random((3, 16, 24)).astype(np.float32)
    hair_pairs.write_pair(tmp_path, 9, features, target, {"style": "wavy"})
    x, y, meta = hair_pairs.read_pair(tmp_path, 9)
    np.testing.assert_allclose(x, features.reshape(24, 16, 24), atol=2e-3)
    np.testing.assert_allclose(y, target, atol=2e-3)
    assert meta["split"] == "validation" and meta["style"] == "wavy"
    assert [hair_pairs.split_of(i) for i in range(20)].count("validation") == 2
    hair_pairs.pair_paths(tmp_path, 3)[0].write_bytes(b"partial")  # EXR without JSON: incomplete
    assert hair_pairs.complete_indices(tmp_path) == [9]


def _tiny_dataset(directory, pairs=10, size=32):
    """Synthetic strands through the real renderer; the 64-sample unfiltered render stands in as target."""
    rng = np.random.default_rng(3)
    curves = [(rng.uniform(-0.1, 0.1, 3), rng.uniform(-0.1, 0.1, 3)) for _ in range(60)]
    strands = straight_strands(curves, radius=0.0008)
    for index in range(pairs):
        camera = hr.random_camera(rng, *strands.bounds(), size)
        light = hr.random_light(rng)
        render = hr.render_stochastic(strands, camera, light, 16, shadow_map_size=128)
        hair_pairs.write_pair(directory, index, render.features[:4], render.unfiltered(), {"style": "synthetic"})


def test_training_checkpoints_resumes_and_exports_a_filter_onnxruntime_agrees_with(tmp_path):
    import torch

    from sg_lightfield.hair import train as hair_train
    from sg_lightfield.hair.unet import HairNetConfig, HairUNet

    _tiny_dataset(tmp_path / "data")
    # What the shipped filters are: a "+blend" network trained with the FLIP term.
    first = hair_train.train(tmp_path / "data", "small+blend", 3.0, tmp_path / "work", batch=4, flip_weight=0.3)
    checkpoint = tmp_path / "work" / "hair_small+blend.ckpt.pt"
    assert checkpoint.is_file() and first["step"] > 0 and first["validation_pairs"] == 1
    assert first["flip_weight"] == 0.3 and np.isfinite(first["best_validation"])
    resumed = hair_train.train(tmp_path / "data", "small+blend", 6.0, tmp_path / "work", resume=True, batch=4,
                               flip_weight=0.3)
    assert resumed["step"] > first["step"]
    assert [h["step"] for h in resumed["history"][:len(first["history"])]] == [h["step"] for h in first["history"]]
    from sg_lightfield.hair.unet import export_onnx

    path = export_onnx(resumed["model"], tmp_path / "small.onnx", metadata={"steps": resumed["step"]})
    hair_filter = load_filter(path)
    assert (hair_filter.config, hair_filter.samples, hair_filter.stride) == ("small+blend", 4, 8)
    x, _, _ = hair_pairs.read_pair(tmp_path / "data", 0)
    x = x[None, :, :30, :27]  # not a multiple of the stride: padded and cropped back
    got, padded = hair_filter.run(x)
    assert padded and got.shape == (3, 30, 27)
    model = resumed["model"].eval()
    with torch.no_grad():
        expected = model(torch.nn.functional.pad(torch.from_numpy(x), (0, 5, 0, 2)))[0, :, :30, :27].numpy()
    np.testing.assert_allclose(got, expected, atol=1e-4, rtol=1e-4)
    bare = HairUNet(HairNetConfig.named("small"))
    torch.onnx.export(bare, torch.zeros(1, 24, 16, 16), str(tmp_path / "foreign.onnx"), dynamo=False)
    with pytest.raises(HairFilterError, match="not an SG Lightfield hair filter"):
        load_filter(tmp_path / "foreign.onnx")


def test_noise_share_predicts_what_sixteen_samples_gain_over_four():
    """Real renders of 320 samples: four blocks of 16 (whose first 4 are the input), and the mean of the last 256
    as the target, also with the hair's colour and highlight scaled by 0.5 and 0.25 (biased inputs). Over the
    blocks, in linear radiance, 1 - 3/4 x share is what 16 samples leave of 4 samples' error; tone-mapped, the
    shares keep the order of what 16 samples gain (the bench's metrics are tone-mapped)."""
    import dataclasses

    from sg_lightfield.bake_directory.image_metrics import tonemap

    rng = np.random.default_rng(5)
    curves = [(rng.uniform(-0.1, 0.1, 3), rng.uniform(-0.1, 0.1, 3)) for _ in range(80)]
    strands = straight_strands(curves, radius=0.0008)
    hair_color, light, grey = hr.EVALUATION_LOOK

    def composite(outputs):
        return hr.composite(outputs, hair_color, np.full(outputs.shape[1:] + (3,), grey), light)

    for _ in range(2):
        render = hr.render_stochastic(strands, hr.random_camera(rng, *strands.bounds(), 48), hr.random_light(rng),
                                      320, shadow_map_size=128)
        blocks = [dataclasses.replace(render, features=render.features[16 * b:16 * b + 16]) for b in range(4)]
        clean = dataclasses.replace(render, features=render.features[64:]).unfiltered()
        shares, tone_mapped_left = [], []
        for scale in (1.0, 0.5, 0.25):
            target = clean * np.array([scale, scale, 1.0])[:, None, None]
            shares.append(np.mean([hair_pairs.noise_share(block.network_input(4)[0], target) for block in blocks]))
            linear, mapped = np.zeros(2), np.zeros(2)
            for block in blocks:
                for i, n in enumerate((4, 16)):
                    image = composite(block.unfiltered(n))
                    linear[i] += ((image - composite(target)) ** 2).sum()
                    mapped[i] += ((tonemap(image) - tonemap(composite(target))) ** 2).sum()
            assert abs((1 - 0.75 * shares[-1]) - linear[1] / linear[0]) < 0.06, (scale, shares[-1], linear)
            tone_mapped_left.append(mapped[1] / mapped[0])
        assert shares[0] > 0.85 and shares[0] > shares[1] > shares[2]
        assert tone_mapped_left[0] < tone_mapped_left[1] < tone_mapped_left[2]
    with pytest.raises(ValueError, match="at least 2 samples"):
        hair_pairs.noise_share(blocks[0].network_input(1)[0], clean)


def test_training_draws_pairs_by_their_noise_share(tmp_path):
    import torch

    from sg_lightfield.hair import train as hair_train

    _tiny_dataset(tmp_path, pairs=4, size=32)
    *_, shares = hair_train.load_pairs(tmp_path, 4, with_noise_shares=True)
    assert shares.shape == (4,) and bool(((shares >= 0) & (shares <= 1)).all())
    assert hair_train.pair_weights(shares, 0.0) is None
    weights = hair_train.pair_weights(torch.tensor([0.1, 0.4, 0.0], dtype=torch.float64), 2.0)
    np.testing.assert_allclose(weights.numpy(), [0.01 / 0.170001, 0.16 / 0.170001, 1e-6 / 0.170001])
    inputs = torch.arange(3.0).view(3, 1, 1, 1).expand(3, 24, 32, 32).contiguous()
    x, _ = hair_train.random_crops(inputs, torch.zeros(3, 3, 32, 32), 200, torch.Generator().manual_seed(0),
                                   weights)
    picked = np.bincount(x[:, 0, 0, 0].abs().long().numpy(), minlength=3)
    assert picked[1] > 150 and picked[2] == 0
    # A step budget: the same run whatever else the machine does (budget_s is ignored).
    result = hair_train.train(tmp_path, "small", 0.0, tmp_path / "work", batch=2, noise_emphasis=1.0, max_steps=7)
    assert result["step"] == 7 and result["noise_emphasis"] == 1.0
    assert result["noise_share_quartiles"] == sorted(result["noise_share_quartiles"])
    assert result["noise_share_quartiles"][0] == pytest.approx(float(shares.min()), abs=1e-3)


def test_training_command_refuses_absurd_budgets_with_one_message(tmp_path, capsys):
    from sg_lightfield.hair import train as hair_train

    for arguments, message in ((["--steps", "0"], "--steps must be at least 1"),
                               (["--budget", "0"], "--budget must be more than 0 seconds"),
                               (["--budget", "nan"], "--budget must be more than 0 seconds"),
                               (["--steps", "5", "--budget", "3"], "not allowed with argument"),
                               (["--noise-emphasis", "9"], "--noise-emphasis must be in 0..8")):
        with pytest.raises(SystemExit) as exit_info:
            hair_train.main(["--data", str(tmp_path), "--out", str(tmp_path / "m.onnx"), *arguments])
        assert exit_info.value.code == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "m.onnx").exists()


def test_bad_model_files_give_one_clear_message(tmp_path):
    with pytest.raises(HairFilterError, match="not found"):
        load_filter(tmp_path / "missing.onnx")
    corrupt = tmp_path / "corrupt.onnx"
    corrupt.write_bytes(SHIPPED_MODEL.read_bytes()[:2000])
    with pytest.raises(HairFilterError, match="not a readable ONNX file"):
        load_filter(corrupt)
    with pytest.raises(HairFilterError, match="unknown hair filter network 'huge'; choose one of base, large"):
        load_filter(network="huge")


@pytest.mark.parametrize("network", sorted(SHIPPED_MODELS))
def test_the_shipped_networks_are_4_spp_filters_with_their_reproduction_recipes(network):
    hair_filter = load_filter(network=network)
    assert (hair_filter.config, hair_filter.samples, hair_filter.stride) == (f"{network}+blend", 4, 8)
    assert hair_filter.path == SHIPPED_MODELS[network]
    recipe = json.loads(SHIPPED_MODELS[network].with_suffix(".json").read_text())
    assert recipe["train_pairs"] >= 100
    assert recipe["step"] == {"base": 20982, "large": 21000}[network]  # base: its 1800-s budget's steps
    makefile = (REPO / "Makefile").read_text()
    assert f"--config {network}+blend " in recipe["command"]
    assert recipe["command"].startswith("python -m hair.train ")
    assert f"--config {network}+blend --flip-weight 0.3 --steps 21000 --out models/hair_{network}.onnx" in makefile
    assert load_filter().path == SHIPPED_MODEL == SHIPPED_MODELS["large"]  # the default


def test_mirrored_input_keeps_tangents_along_the_strands_in_the_image():
    """A diagonal strand: in the render and in each of its mirror images, the view-space tangent features of
    the covered pixels point along the line those pixels form (x right, y up)."""
    strands = straight_strands([((-0.06, 0.0, -0.03), (0.06, 0.0, 0.04))], radius=0.0008)
    render = hr.render_stochastic(strands, front_camera(64, 0.2), (0, -1, 0), 2, shadow_map_size=64)
    features = render.network_input()
    tx, ty = hr.FEATURE_NAMES.index("tangent_x"), hr.FEATURE_NAMES.index("tangent_y")
    for left_right in (False, True):
        for up_down in (False, True):
            mirrored = mirror_features(features, left_right, up_down)[0]
            covered = mirrored[hr.FEATURE_NAMES.index("alpha")] > 0
            rows, cols = np.nonzero(covered)
            points = np.stack([cols, -rows], axis=1).astype(float)
            line = np.linalg.svd(points - points.mean(0))[2][0]
            tangents = np.stack([mirrored[tx][covered], mirrored[ty][covered]], axis=1)
            tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
            assert np.abs(tangents @ line).min() > 0.98, (left_right, up_down)
            np.testing.assert_array_equal(mirror_features(mirrored, left_right, up_down), features[0])


def test_the_mean_over_mirror_passes_composites_as_the_mean_of_composites():
    rng = np.random.default_rng(3)
    outputs = [np.stack([rng.uniform(0, 2, (5, 7)), rng.uniform(0, 1, (5, 7)), rng.uniform(-0.2, 1.2, (5, 7))])
               for _ in range(4)]
    outputs[0][2, 0, 0] = outputs[1][2, 0, 0] = outputs[2][2, 0, 0] = outputs[3][2, 0, 0] = 0.0  # no hair
    background = rng.uniform(0, 1, (5, 7, 3))
    look = dict(hair_color=(0.3, 0.2, 0.1), background=background, light=2.5)
    expected = np.mean([hr.composite(o, **look) for o in outputs], axis=0)
    np.testing.assert_allclose(hr.composite(mean_as_composited(outputs), **look), expected, rtol=1e-12, atol=1e-12)


def test_mirror_passes_of_the_shipped_filter(tmp_path):
    """One pass is the network's output; four passes are equivariant: filtering the mirror image gives the
    mirror image of the filtered result. Anything but 1, 2 or 4 passes is refused with one clear message."""
    strands = straight_strands([((-0.08, 0.0, -0.05 + 0.01 * k), (0.07, 0.01 * k, 0.06 - 0.015 * k))
                                for k in range(6)], radius=0.0007)
    render = hr.render_stochastic(strands, front_camera(44, 0.2), (0.3, -1, 0.5), 4, shadow_map_size=128)
    hair_filter = load_filter()
    one, _ = hair_filter.filter(render, passes=1)
    network, _ = hair_filter.run(render.network_input())
    covered = one[2] > 0
    np.testing.assert_array_equal(one[:, covered], network[:, covered])
    four, padded = hair_filter.filter(render, passes=4)
    assert padded and four.shape == one.shape and np.isfinite(four).all()
    assert np.abs(four - one).max() > 1e-3  # the passes do differ
    mirrored_features = mirror_features(render.features, True, False)
    mirrored = hr.StochasticRender(mirrored_features, render.fragment_count, render.depth_range,
                                   {"footprint": render.extras["footprint"][:, ::-1]})
    four_of_mirror, _ = hair_filter.filter(mirrored, passes=4)
    np.testing.assert_allclose(unmirror(four_of_mirror, True, False), four, atol=2e-5)
    with pytest.raises(HairFilterError, match="filter passes must be one of"):
        hair_filter.filter(render, passes=3)


# ------------------------------------------------------------------ Blender: reference, operator, CLI

@pytest.mark.slow
def test_cycles_reference_and_our_renderer_describe_the_same_shading():
    """Thin unoccluded strands (opacity 0.05): Cycles' colour factor and highlight (256 spp) match the lobes our
    renderer computes; on the demo groom (opacity 0.7, self-shadowing) the premultiplied means agree."""
    import bpy

    from sg_lightfield.hair import blender_scene as hair
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.scene_analysis import active_scene

    scene = build_demo_scene("demo:hair")
    objects = hair.hair_objects(scene)
    with active_scene(scene):
        depsgraph = bpy.context.evaluated_depsgraph_get()
        strands = hair.strands_from_objects(objects, depsgraph)
        camera = hair.pinhole_camera(scene, depsgraph, width=64, height=64)
    for opacity, tolerance in ((0.05, 0.08), (0.7, 0.08)):  # measured 2-6 % over groom builds
        shading = hr.HairShading(opacity=opacity)
        for light in ((0.3, -1.0, 0.4), (0.2, 1.0, 0.3)):
            light = np.array(light) / np.linalg.norm(light)
            reference = hair.render_reference(objects, camera, light, samples=256, shading=shading)
            ours = hr.render_stochastic(strands, camera, light, 128, shading=shading).unfiltered()
            for channel in range(2):
                ref_mean = (reference[channel] * reference[2]).mean()
                our_mean = (ours[channel] * ours[2]).mean()
                assert abs(our_mean / ref_mean - 1) < tolerance + (0.1 if channel == 1 else 0), \
                    (opacity, light, channel, ref_mean, our_mean)
            assert abs(ours[2].mean() / reference[2].mean() - 1) < 0.06


@pytest.mark.slow
def test_filter_hair_operator_on_the_hair_scene(tmp_path):
    import bpy

    from sg_lightfield import blender_addon
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene
    from sg_lightfield.blender_addon.scene_analysis import active_scene
    from sg_lightfield.bake_directory.exr_io import read_exr

    blender_addon.register()
    try:
        scene = build_demo_scene("demo:hair")
        with active_scene(scene):
            scene.render.resolution_x, scene.render.resolution_y = 100, 75  # not a multiple of 8
            scene.render.resolution_percentage = 100
            scene.sg_lightfield.hair_output_dir = str(tmp_path / "hair")
            scene.sg_lightfield.hair_background_samples = 4
            scene.sg_lightfield.hair_filter_passes = "2"
            assert bpy.ops.sg_lightfield.filter_hair() == {"FINISHED"}
        image = bpy.data.images["Filtered Hair"]
        assert tuple(image.size) == (100, 75)
        pixels, _, _ = read_exr(tmp_path / "hair" / "filtered.exr")
        assert pixels.shape == (75, 100, 3) and np.isfinite(pixels).all()
        summary = json.loads((tmp_path / "hair" / "hair_filter.json").read_text())
        assert summary["key_light"].startswith("Key") and any("stride" in w for w in summary["warnings"])
        assert summary["filter_passes"] == 2 and summary["config"] == "large+blend"  # the default network
        assert summary["model"].endswith("hair_large.onnx")
        with active_scene(scene):
            scene.sg_lightfield.hair_network = "BASE"
            assert bpy.ops.sg_lightfield.filter_hair() == {"FINISHED"}
        summary = json.loads((tmp_path / "hair" / "hair_filter.json").read_text())
        assert summary["config"] == "base+blend" and summary["model"].endswith("hair_base.onnx")
        empty = build_demo_scene("demo:spheres")
        with active_scene(empty):
            empty.sg_lightfield.hair_output_dir = str(tmp_path / "none")
            with pytest.raises(RuntimeError, match="no hair to filter"):
                bpy.ops.sg_lightfield.filter_hair()
    finally:
        blender_addon.unregister()


@pytest.mark.slow
def test_filter_hair_command_line_and_its_bad_input(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, str(REPO / "headless" / "filter_hair.py"), *args],
                              capture_output=True, text=True, timeout=300)

    ok = run("--scene", "demo:hair", "--out", str(tmp_path / "ok"), "--width", "64", "--height", "48",
             "--background-samples", "2")
    assert ok.returncode == 0, ok.stderr
    assert (tmp_path / "ok" / "filtered.png").is_file() and (tmp_path / "ok" / "unfiltered.png").is_file()
    summary = json.loads((tmp_path / "ok" / "hair_filter.json").read_text())
    assert summary["filter_passes"] == 4 and summary["config"] == "large+blend"  # the defaults
    no_hair = run("--scene", "demo:spheres", "--out", str(tmp_path / "x"))
    assert no_hair.returncode == 1 and no_hair.stderr.strip().splitlines()[-1].startswith("error: ")
    (tmp_path / "bad.onnx").write_text("not a model")
    bad = run("--scene", "demo:hair", "--out", str(tmp_path / "x"), "--model", str(tmp_path / "bad.onnx"))
    assert bad.returncode == 1 and "not a readable ONNX file" in bad.stderr
    both = run("--scene", "demo:hair", "--out", str(tmp_path / "x"), "--network", "large", "--model", "m.onnx")
    assert both.returncode == 2 and "not allowed with argument" in both.stderr
    assert not (tmp_path / "x" / "filtered.exr").exists()


def test_random_views_are_drawn_again_until_strands_are_in_view():
    """Two short strands at opposite corners of a 1 m box: most close-ups aim between them. random_view keeps
    drawing from the same generator until a strand crosses a pixel, and its first draw is random_camera's and
    random_light's (so views that showed hair stay what earlier datasets hold)."""
    strands = straight_strands([((-0.5, -0.5, -0.5), (-0.45, -0.5, -0.5)), ((0.45, 0.5, 0.5), (0.5, 0.5, 0.5))])
    options = {"shadow_map_size": 64}
    draws_seen = []
    for seed in range(6):
        camera, light, render, draws = hr.random_view(np.random.default_rng(seed), strands, 32, 2, tries=400, **options)
        assert render.fragment_count > 0
        replay = np.random.default_rng(seed)
        for draw in range(draws):
            replayed_camera = hr.random_camera(replay, *strands.bounds(), 32)
            replayed_light = hr.random_light(replay)
            if draw < draws - 1:
                assert hr.render_stochastic(strands, replayed_camera, replayed_light, 2, **options).fragment_count == 0
        np.testing.assert_array_equal(replayed_camera.world_to_camera, camera.world_to_camera)
        np.testing.assert_array_equal(replayed_light, light)
        draws_seen.append(draws)
    assert max(draws_seen) > 1
    with pytest.raises(ValueError, match="none of 1 random views"):
        hr.random_view(np.random.default_rng(int(np.argmax(draws_seen))), strands, 32, 2, tries=1, **options)


def test_the_bench_scores_unseen_views_of_the_trained_styles_and_pairs_methods_per_view():
    from sg_lightfield.hair import blender_scene as hair
    from sg_lightfield.headless import hair_dataset
    from sg_lightfield.headless.bench_hair import paired_differences, unseen_view_jobs

    unseen = unseen_view_jobs(9)
    in_dataset = {(name, index) for name, index, _ in hair_dataset.dataset_jobs(hair_dataset.PAIRS,
                                                                                hair_dataset.HELD_OUT)}
    assert len(unseen) == 9 and not in_dataset & {(name, index) for name, index, _ in unseen}
    assert all(name == "train" and index >= hair_dataset.PAIRS for name, index, _ in unseen)
    styles = [style for *_, style in unseen]
    assert sorted(set(styles)) == sorted(hair.TRAIN_STYLES) and hair.HELD_OUT_STYLE not in styles
    assert all(styles.count(style) == 3 for style in hair.TRAIN_STYLES)
    # FLIP lower and PSNR higher are "ours better"; the standard error is of the per-view differences.
    scores = {"ours": {"flip": [0.10, 0.20, 0.30], "psnr": [30.0, 31.0, 29.0]},
              "other": {"flip": [0.12, 0.21, 0.29], "psnr": [29.0, 29.0, 29.0]}}
    row = paired_differences(scores, "ours", ("other", "absent"))["ours vs other"]
    assert row["flip"]["mean_gain"] == pytest.approx(0.02 / 3, abs=1e-5) and row["flip"]["wins"] == 2
    assert row["flip"]["standard_error"] == pytest.approx(np.std([0.02, 0.01, -0.01], ddof=1) / np.sqrt(3), abs=1e-5)
    assert row["psnr"]["mean_gain"] == pytest.approx(1.0) and row["psnr"]["wins"] == 2


@pytest.mark.slow
def test_dataset_generation_is_resumable(tmp_path):
    def run():
        return subprocess.run([sys.executable, str(REPO / "headless" / "hair_dataset.py"), "--out",
                               str(tmp_path), "--pairs", "2", "--held-out", "1", "--size", "32",
                               "--reference-samples", "4", "--density", "5000"],
                              capture_output=True, text=True, timeout=300)

    first = run()
    assert first.returncode == 0, first.stderr
    assert "3 made, 0 already there" in first.stdout
    assert hair_pairs.complete_indices(tmp_path / "train") == [0, 1]
    assert json.loads((tmp_path / "held_out" / "pair_00000.json").read_text())["style"] == "clumped"
    (tmp_path / "train" / "pair_00001.json").unlink()  # as if interrupted while writing pair 1
    second = run()
    assert "1 made, 2 already there" in second.stdout

    # The bench draws the same views from the seeds alone, without the files. The groom is built again, and at
    # this low density its bounds move by ~1 % between builds, so the camera that frames them moves as much.
    from sg_lightfield.hair import blender_scene as hair
    from sg_lightfield.blender_addon.scene_analysis import active_scene
    from sg_lightfield.headless.hair_dataset import dataset_view

    scene, objects = hair.dataset_groom("clumped", 5000.0)
    with active_scene(scene):
        import bpy
        strands = hair.strands_from_objects(objects, bpy.context.evaluated_depsgraph_get())
    meta = json.loads((tmp_path / "held_out" / "pair_00000.json").read_text())
    camera, light, render, draws = dataset_view(strands, "held_out", 0, size=32)
    assert draws == meta["view_draws"] and render.fragment_count > 0
    np.testing.assert_array_equal(light, meta["light"])
    np.testing.assert_allclose(camera.world_to_camera, meta["world_to_camera"], atol=0.1)
    assert camera.focal_px == pytest.approx(meta["focal_px"], rel=0.1)
    other, *_ = dataset_view(strands, "train", 0, size=32)  # the split is part of the seed
    assert not np.allclose(other.world_to_camera, camera.world_to_camera, atol=0.1)


@pytest.mark.slow
def test_two_differently_coloured_grooms_are_said_and_coloured_per_pixel(tmp_path):
    import bpy

    from sg_lightfield.hair import blender_scene as hair
    from sg_lightfield.blender_addon.demo_scenes import build_demo_scene

    scene = build_demo_scene("demo:hair")
    first = hair.hair_objects(scene)[0]
    second = first.copy()  # same strands, moved aside, with its own blond material
    second.data = first.data.copy()
    blond = first.active_material.copy()
    next(n for n in blond.node_tree.nodes if n.type == "BSDF_HAIR_PRINCIPLED").inputs["Color"].default_value = \
        (0.9, 0.75, 0.4, 1.0)
    second.data.materials[0] = blond
    second.location.x += 0.12
    scene.collection.objects.link(second)
    result = hair.filter_hair(scene, tmp_path, width=64, height=48, background_samples=1)
    assert any("2 hair objects with different colours" in w for w in result.warnings)
    # The blond groom (right half of the frame) shows up brighter than the brown one where hair covers.
    alpha = result.outputs[2]
    left, right = result.image[:, :20][alpha[:, :20] > 0.5], result.image[:, 44:][alpha[:, 44:] > 0.5]
    assert left.size and right.size and right.mean() > left.mean()
