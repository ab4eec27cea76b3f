"""Fitting N free spherical Gaussians to per-texel light-field images (Paper I section 4, DESIGN section 5).

Two optimisers share the parameterisation, the loss and the initialisation of the parameter read-out:
  * the paper's CNN encoder (one network per scene, shared by every texel), and
  * per-texel gradient descent on the same parameters (a baseline), optionally with the regulariser
    that pulls the axes of neighbouring texels together.

Parameters per SG: unit axis (3), sharpness (1), amplitude (C: 3 for RGB light fields, 1 for mono IWEV). Constraints by reparameterisation:
axis = normalise(raw), sharpness = exp(a sigmoid between log SHARPNESS_MIN and log SHARPNESS_MAX),
amplitude = softplus(raw) * amplitude_scale (a data scale; the half-float packing scale comes at export).
Loss (per pixel and channel): (log(1 + T) - log(1 + P))^2 weighted by the pixel's exact solid angle,
P evaluated at a direction jittered uniformly inside the pixel, zero below the texel's normal.
Interpolation term (TrainConfig.interpolation_weight > 0, both optimisers alike): for each texel of a step, one
adjacent texel of the same object; the same loss for their blended parameters (as the node group's bilinear lookup
blends them, `blend_parameters`) against their blended light fields, over directions above both horizons. It asks
what the midpoint metric measures, from the training light fields alone (the held-out midpoints stay unseen).
"""
from __future__ import annotations

import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..bake_directory.atomic import atomic_output
from ..shaders.octahedral import pixel_directions
from ..shaders.octahedral import pixel_solid_angles as exact_solid_angles
from ..shaders.sg_math import SHARPNESS_MAX, SHARPNESS_MIN, midpoint_parameters, unit_midpoint  # noqa: F401
from .sg_torch import oct_decode, pixel_solid_angles, safe_normalize

LOG_SHARPNESS_MIN, LOG_SHARPNESS_MAX = math.log(SHARPNESS_MIN), math.log(SHARPNESS_MAX)


def params_per_sg(channels: int = 3) -> int:
    return 4 + channels


@dataclass
class TrainConfig:
    sg_count: int = 16
    time_budget_s: float = 60.0
    max_epochs: int = 100_000
    batch_texels: int = 256
    # On CUDA a step takes up to this many texels x light-field pixels (the whole atlas where it fits: room at Draft,
    # 4096 texels at R = 32): a GPU's step costs about the same for 256 texels as for thousands.
    cuda_batch_pixels: int = 1 << 22
    cuda_batch_learning_rate: float = 1e-3  # the rate for those larger steps
    cuda_graphs: bool = True  # the CNN's whole step as one CUDA graph (not with the interpolation term)
    learning_rate: float = 1e-3
    seed: int = 0
    device: str = "cpu"
    # Stop when the mean loss of the last window has not improved on the window before by plateau_rel; the window is
    # plateau_epochs, or more epochs when needed to hold plateau_steps optimiser steps (small bakes: short epochs).
    plateau_epochs: int = 40
    plateau_steps: int = 2000
    plateau_rel: float = 1e-3
    # ... or when the rest of the budget would gain less than this share of the loss, the last window's gain per
    # second extrapolated linearly (more than a slowing curve gives): a fast device stops before its budget ends.
    plateau_budget_rel: float = 0.01
    below_horizon_weight: float = 0.0  # 0 = the paper's loss
    interpolation_weight: float = 0.0  # 0 = the paper's loss; > 0 adds the interpolation term (needs neighbours)
    checkpoint_every_s: float = 30.0
    lr_drop_on_nan: float = 0.5


@dataclass
class TrainState:
    epoch: int = 0
    losses: list = field(default_factory=list)  # mean training loss per epoch
    seconds: list = field(default_factory=list)  # cumulative training seconds at the end of each epoch
    nan_recoveries: int = 0
    stopped_because: str = ""


@dataclass
class LightFieldData:
    """Per-texel training data: images (T, R, R, C) radiance, normals (T, 3)."""

    images: torch.Tensor
    normals: torch.Tensor
    lobe_counts: torch.Tensor | None = None  # (T,) SGs each texel may use (its material's N); None = all

    @property
    def resolution(self) -> int:
        return int(self.images.shape[1])

    @property
    def channels(self) -> int:
        return int(self.images.shape[-1])

    @classmethod
    def from_numpy(cls, images, normals, device="cpu", lobe_counts=None):
        images = np.maximum(np.nan_to_num(np.asarray(images, np.float32), nan=0.0, posinf=0.0, neginf=0.0), 0.0)
        normals = np.asarray(normals, np.float32).reshape(-1, 3)
        counts = None if lobe_counts is None else torch.from_numpy(np.asarray(lobe_counts, np.int64)).to(device)
        return cls(torch.from_numpy(images).to(device), torch.from_numpy(normals).to(device), counts)


def amplitude_scale_for(images: torch.Tensor) -> float:
    """A data scale for amplitudes so the network's raw outputs start near 1: the 99th percentile."""
    positive = images[images > 0]
    if positive.numel() == 0:
        return 1.0
    sample = positive.flatten()[:: max(1, positive.numel() // 1_000_000)]
    return float(max(torch.quantile(sample.float(), 0.99).item(), 1e-6))


def constrain(raw: torch.Tensor, amplitude_scale: float):
    """Raw (..., N, 4 + C) -> unit axis (..., N, 3), sharpness (..., N), amplitude (..., N, C)."""
    axis = safe_normalize(raw[..., 0:3])
    log_sharpness = LOG_SHARPNESS_MIN + (LOG_SHARPNESS_MAX - LOG_SHARPNESS_MIN) * torch.sigmoid(raw[..., 3] - 1.0)
    sharpness = torch.exp(log_sharpness)
    amplitude = nn.functional.softplus(raw[..., 4:]) * amplitude_scale
    return axis, sharpness, amplitude


def initial_amplitude_fraction(data: "LightFieldData", amplitude_scale: float) -> float:
    """The data's mean radiance over the texels' upper hemispheres as a fraction of the amplitude scale (its 99th
    percentile), at most INITIAL_AMPLITUDE_MAX. Lobes that tile the sphere at this amplitude predict the mean: a
    neutral start. A fixed 0.3 overshot sparse light fields (thin emitters, R = 32 spheres: mean = 0.025 x the
    scale) 12-fold, and the CNN escaped the overshoot by making every lobe maximally sharp and dark, never to recover
    (the baked spheres rendered black)."""
    whole_sphere = (data.normals.abs().sum(-1) == 0).float()
    share_above = float((0.5 + 0.5 * whole_sphere).mean())  # pixels a texel's horizon keeps, roughly
    mean = float(data.images.float().mean()) / max(share_above, 1e-3)
    return float(min(max(mean / max(amplitude_scale, 1e-12), INITIAL_AMPLITUDE_MIN), INITIAL_AMPLITUDE_MAX))


INITIAL_AMPLITUDE_MIN, INITIAL_AMPLITUDE_MAX = 1e-4, 0.3


def initial_raw(sg_count: int, channels: int = 3, amplitude_fraction: float = INITIAL_AMPLITUDE_MAX) -> torch.Tensor:
    """Raw parameters (N, 4 + C) both optimisers start from: axes on a Fibonacci sphere, sharpness N/2 (lobes that
    tile the sphere), amplitudes `amplitude_fraction` x the data scale."""
    from ..shaders.quadrature import fibonacci_sphere

    axes = torch.tensor(fibonacci_sphere(sg_count)[0], dtype=torch.float32)
    fraction = (math.log(max(sg_count / 2.0, 1.0)) - LOG_SHARPNESS_MIN) / (LOG_SHARPNESS_MAX - LOG_SHARPNESS_MIN)
    sharpness = math.log(fraction / (1 - fraction)) + 1.0
    amplitude = math.log(math.expm1(amplitude_fraction))
    raw = torch.empty((sg_count, params_per_sg(channels)))
    raw[:, 0:3], raw[:, 3], raw[:, 4:] = axes, sharpness, amplitude
    return raw


def jittered_directions(batch: int, resolution: int, generator: torch.Generator | None, device="cpu"):
    """(B, R, R, 3) directions uniform inside each octahedral pixel (fresh for every step), drawn on `device`
    (`generator` None: that device's default generator, which a CUDA graph can capture)."""
    centres = (torch.arange(resolution, dtype=torch.float32, device=device) + 0.5) / resolution * 2 - 1
    v, u = torch.meshgrid(centres, centres, indexing="ij")
    jitter = (torch.rand((batch, resolution, resolution, 2), generator=generator, device=device) - 0.5) * (
        2.0 / resolution)
    uv = torch.stack([u, v], dim=-1)[None] + jitter
    return oct_decode(uv.clamp(-1.0, 1.0))


def blend_parameters(params_a, params_b):
    """Torch twin of `midpoint_parameters`: the parameters halfway between two texels as the node group's bilinear
    lookup gives them (axes blended and renormalised, sharpness blended in its log encoding, amplitudes blended)."""
    (axis_a, sharpness_a, amplitude_a), (axis_b, sharpness_b, amplitude_b) = params_a, params_b
    total = axis_a + axis_b  # opposite axes blend to the zero vector, as the node group normalises it
    axis = total / torch.linalg.vector_norm(total, dim=-1, keepdim=True).clamp_min(1e-8)
    return axis, torch.sqrt(sharpness_a * sharpness_b), 0.5 * (amplitude_a + amplitude_b)


def predict(params, directions):
    """Sum of SGs at directions (B, R, R, 3) for params ((B,N,3), (B,N), (B,N,C)) -> (B, R, R, C).

    `sg_sum_eval` as two batched matrix products: the cosines (B, P, 3) x (B, 3, N) and the lobes' values
    (B, P, N) x amplitudes (B, N, C); broadcasting to (B, P, N, C) and summing over N cost 2.5x the time."""
    axis, sharpness, amplitude = params
    flat = directions.reshape(directions.shape[0], -1, 3)
    cos = torch.bmm(flat, axis.transpose(1, 2)).clamp(-1.0, 1.0)
    lobes = torch.exp(sharpness[:, None, :] * (cos - 1.0))
    return torch.bmm(lobes, amplitude).reshape(*directions.shape[:-1], amplitude.shape[-1])


def _above_horizon(directions, normals):
    """(B, R, R) directions above each texel's horizon; a zero normal has none (the environment: whole sphere)."""
    whole_sphere = (normals.abs().sum(-1) == 0)[:, None, None]
    return ((directions * normals[:, None, None, :]).sum(-1) > 0) | whole_sphere


def lightfield_loss(params, target, normals, directions, solid_angles, below_weight: float = 0.0,
                    other_normals=None, texel_weight=None):
    """Solid-angle-weighted log-L2 over the upper hemisphere; returns (loss, weight sum).

    below_weight > 0 also pulls the prediction towards 0 below the texel's horizon (the rendered image is 0
    there): the paper gives those directions no gradient, which leaves lobes there unconstrained, and a
    neighbour whose horizon differs sees them after interpolation. other_normals (B, 3): count only directions
    above both horizons (a blend of two texels' light fields). texel_weight (B,): per-texel weights."""
    prediction = predict(params, directions)
    above = _above_horizon(directions, normals)
    if other_normals is not None:
        above = above & _above_horizon(directions, other_normals)
    weight = solid_angles[None] * torch.where(above, 1.0, below_weight)
    if texel_weight is not None:
        weight = weight * texel_weight[:, None, None]
    error = (torch.log1p(target) - torch.log1p(prediction.clamp_min(0))) ** 2
    total = (error.mean(dim=-1) * weight).sum()
    return total / weight.sum().clamp_min(1e-12), weight.sum()


class SGEncoder(nn.Module):
    """Paper I encoder: [conv 3x3 + ReLU + max-pool 2x2] blocks (32 channels, doubling) down to 4x4 (at most
    four blocks), then one fully connected layer to N x (4 + C) parameters."""

    def __init__(self, resolution: int, sg_count: int, in_channels: int = 3,
                 amplitude_fraction: float = INITIAL_AMPLITUDE_MAX):
        super().__init__()
        if resolution < 8 or resolution & (resolution - 1):
            raise ValueError(f"light-field resolution {resolution} must be a power of two >= 8")
        layers, channels, size = [], in_channels, resolution
        width = 32
        while size > 4 and len(layers) < 4 * 3:
            layers += [nn.Conv2d(channels, width, 3, padding=1), nn.ReLU(), nn.MaxPool2d(2)]
            channels, size, width = width, size // 2, width * 2
        self.features = nn.Sequential(*layers)
        self.per_sg = params_per_sg(in_channels)
        self.head = nn.Linear(channels * size * size, sg_count * self.per_sg)
        with torch.no_grad():  # start every texel at the shared initial read-out, small input dependence
            self.head.weight.mul_(0.1)
            self.head.bias.copy_(initial_raw(sg_count, in_channels, amplitude_fraction).flatten())
        self.sg_count = sg_count

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """images (B, R, R, C) radiance -> raw parameters (B, N, 4 + C)."""
        x = torch.log1p(images.clamp_min(0)).permute(0, 3, 1, 2)
        x = self.features(x).flatten(1)
        return self.head(x).view(-1, self.sg_count, self.per_sg)


class PerTexelParameters(nn.Module):
    """The per-texel gradient-descent baseline: raw parameters for every texel, same read-out."""

    def __init__(self, texels: int, sg_count: int, generator: torch.Generator, channels: int = 3,
                 amplitude_fraction: float = INITIAL_AMPLITUDE_MAX):
        super().__init__()
        noise = torch.randn((texels, sg_count, params_per_sg(channels)), generator=generator) * 0.05
        self.raw = nn.Parameter(initial_raw(sg_count, channels, amplitude_fraction)[None] + noise)

    def forward(self, index: torch.Tensor) -> torch.Tensor:
        return self.raw[index]


def _atomic_torch_save(obj, path: Path):
    with atomic_output(path) as tmp:
        torch.save(obj, tmp)


class Trainer:
    """Trains the CNN (mode 'cnn') or the per-texel baseline (mode 'per_texel') on LightFieldData.

    Deterministic on the CPU for a seed; checkpoints (model, optimiser, RNG, curve) resume the same curve."""

    def __init__(self, data: LightFieldData, config: TrainConfig, mode: str = "cnn", neighbours=None,
                 axis_alignment: float = 0.0, checkpoint: Path | None = None):
        if mode not in ("cnn", "per_texel"):
            raise ValueError(f"mode must be 'cnn' or 'per_texel', got {mode!r}")
        self.data, self.config, self.mode = data, config, mode
        self.checkpoint = Path(checkpoint) if checkpoint else None
        self.device = torch.device(config.device)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator(device="cpu").manual_seed(config.seed)
        self.amplitude_scale = amplitude_scale_for(data.images)
        fraction = initial_amplitude_fraction(data, self.amplitude_scale)
        if mode == "cnn":
            self.model = SGEncoder(data.resolution, config.sg_count, data.channels, fraction).to(self.device)
        else:
            self.model = PerTexelParameters(len(data.images), config.sg_count, self.generator,
                                            data.channels, fraction).to(self.device)
        self.batch_texels = self._batch_for_device()
        rate = config.learning_rate if self.batch_texels <= config.batch_texels else config.cuda_batch_learning_rate
        # Fused Adam skips a step on its device when `found_inf` is set: no host synchronisation per step.
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=rate, fused=True,
                                          capturable=self.device.type == "cuda")
        self._graph = None  # the captured CUDA step, its index buffer and accumulators (see _graph_epoch)
        self.graph_error = ""  # why CUDA graphs are not used, where they were asked for and failed
        self._last_snapshot = None
        self.solid_angles = pixel_solid_angles(data.resolution, device=self.device)
        self.neighbours = neighbours  # (M, 2) adjacent texel index pairs: axis-alignment and interpolation terms
        self.axis_alignment = axis_alignment
        self._partners = None
        if config.interpolation_weight > 0:
            if neighbours is None:
                raise ValueError("the interpolation term needs the texels' neighbour pairs")
            self._partners = _partner_table(torch.as_tensor(neighbours, dtype=torch.int64), len(data.images))
        self.state = TrainState()
        if self.checkpoint is not None and self.checkpoint.is_file():
            self._load(self.checkpoint)

    # --- parameters --------------------------------------------------------------------------------
    def raw_parameters(self, index: torch.Tensor) -> torch.Tensor:
        if self.mode == "cnn":
            return self.model(self.data.images[index].to(self.device))
        return self.model(index.to(self.device))

    def constrained_parameters(self, index: torch.Tensor):
        """axis, sharpness, amplitude of the texels `index`; SGs beyond a texel's lobe count have zero amplitude."""
        axis, sharpness, amplitude = constrain(self.raw_parameters(index), self.amplitude_scale)
        if self.data.lobe_counts is not None:
            slots = torch.arange(amplitude.shape[1], device=amplitude.device)
            used = slots[None, :] < self.data.lobe_counts[index].to(amplitude.device)[:, None]
            amplitude = amplitude * used[..., None]
        return axis, sharpness, amplitude

    @torch.no_grad()
    def parameters_numpy(self, batch: int = 1024):
        """Constrained parameters of every texel as numpy: axis (T,N,3), sharpness (T,N), amplitude (T,N,C).
        Texels that received no light at all get exactly zero amplitudes."""
        axes, sharpness, amplitude = [], [], []
        for start in range(0, len(self.data.images), batch):
            index = torch.arange(start, min(start + batch, len(self.data.images)))
            a, s, m = self.constrained_parameters(index)
            black = self.data.images[index].flatten(1).amax(dim=1) <= 0
            m = torch.where(black[:, None, None].to(m.device), torch.zeros_like(m), m)
            axes.append(a.cpu().numpy()), sharpness.append(s.cpu().numpy()), amplitude.append(m.cpu().numpy())
        return np.concatenate(axes), np.concatenate(sharpness), np.concatenate(amplitude)

    # --- training ----------------------------------------------------------------------------------
    def _batch_loss(self, index: torch.Tensor):
        if self._partners is not None:  # each texel of the step and one random neighbour of it
            partner, paired = self._random_partners(index)
            index = torch.cat([index, partner])
        target = self.data.images[index].to(self.device)
        normals = self.data.normals[index].to(self.device)
        generator = self.generator if self.device.type == "cpu" else None
        directions = jittered_directions(len(index), self.data.resolution, generator, self.device)
        params = self.constrained_parameters(index)
        loss, _ = lightfield_loss(params, target, normals, directions, self.solid_angles,
                                  self.config.below_horizon_weight)
        if self._partners is not None and bool(paired.any()):
            n = len(partner)
            blended = blend_parameters(tuple(p[:n] for p in params), tuple(p[n:] for p in params))
            interpolation, _ = lightfield_loss(blended, 0.5 * (target[:n] + target[n:]), normals[:n], directions[:n],
                                               self.solid_angles, other_normals=normals[n:],
                                               texel_weight=paired.to(self.device, torch.float32))
            loss = loss + self.config.interpolation_weight * interpolation
        if self.mode == "per_texel" and self.axis_alignment > 0 and self.neighbours is not None:
            loss = loss + self.axis_alignment * self._alignment_penalty(index)
        return loss

    def _random_partners(self, index):
        """One uniformly chosen neighbour of each texel (itself where it has none) and whether it had one."""
        targets, offsets, counts = self._partners
        count = counts[index]
        pick = (torch.rand(len(index), generator=self.generator) * count).long().clamp_max(count.clamp_min(1) - 1)
        slot = (offsets[index] + pick).clamp(0, max(len(targets) - 1, 0))
        paired = count > 0
        partner = torch.where(paired, targets[slot], index) if len(targets) else index.clone()
        return partner, paired

    def _batch_for_device(self) -> int:
        """The configured batch; for the CNN on CUDA as many texels as `cuda_batch_pixels` allows, the whole atlas
        at most."""
        batch = self.config.batch_texels
        if self.device.type == "cuda" and self.mode == "cnn":
            batch = max(batch, self.config.cuda_batch_pixels // self.data.resolution ** 2)
        return max(1, min(batch, len(self.data.images)))

    def _texels_per_step(self) -> int:
        """Texels a step starts from (half the batch with the interpolation term: the other half are partners)."""
        return max(1, self.batch_texels // 2) if self._partners is not None else self.batch_texels

    def _uses_graph(self) -> bool:
        return (self.device.type == "cuda" and self.config.cuda_graphs and not self.graph_error and self.mode == "cnn"
                and self._partners is None)

    def _alignment_penalty(self, index):
        """Mean over neighbour pairs inside the batch of (1 - a_j . b_j) per SG slot (Paper I's 'aligned axes')."""
        inside = torch.zeros(len(self.data.images), dtype=torch.bool)
        inside[index] = True
        pairs = self.neighbours[inside[self.neighbours[:, 0]] & inside[self.neighbours[:, 1]]]
        if len(pairs) == 0:
            return torch.zeros((), device=self.device)
        a = safe_normalize(self.model.raw[pairs[:, 0], :, 0:3])
        b = safe_normalize(self.model.raw[pairs[:, 1], :, 0:3])
        return (1 - (a * b).sum(-1)).mean()

    def _step(self, index):
        """One Adam step on the texels `index`; returns its share of the epoch's sums (loss x texels, texels kept,
        steps skipped) as a device tensor and never synchronises with the host. A step whose loss or gradients are
        not finite changes nothing: fused Adam skips it on the device (`found_inf`), and it counts as skipped."""
        loss = self._batch_loss(index)
        loss.backward()
        grads = [p.grad for p in self.model.parameters() if p.grad is not None]
        # one norm over every gradient: NaN or infinity anywhere makes it non-finite
        bad = (~torch.isfinite(loss.detach() + torch.nn.utils.get_total_norm(grads, norm_type=1.0))).float()
        self.optimizer.found_inf = bad
        self.optimizer.step()
        return torch.stack([torch.where(bad > 0, 0.0, loss.detach()) * len(index), (1.0 - bad) * len(index), bad])

    def _eager_epoch(self, order, batch, sums):
        for start in range(0, len(order), batch):
            index = order[start:start + batch]
            self.optimizer.zero_grad(set_to_none=True)
            sums += self._step(index)

    def _graph_epoch(self, order, batch, sums):
        """The epoch as replays of one captured CUDA graph (forward, backward, fused Adam, the sums): one launch a
        step. The order is padded to whole batches with its own start. The first capture runs three eager warm-up
        steps first (CUDA's recipe); they train and count like any step."""
        if self._graph is None:
            index = order[:batch].clone()
            side = torch.cuda.Stream(self.device)
            side.wait_stream(torch.cuda.current_stream(self.device))
            with torch.cuda.stream(side):
                for _ in range(3):
                    self.optimizer.zero_grad(set_to_none=True)
                    sums += self._step(index)
            torch.cuda.current_stream(self.device).wait_stream(side)
            self.optimizer.zero_grad(set_to_none=True)
            step_sums = torch.zeros(3, device=self.device)
            graph = torch.cuda.CUDAGraph()
            with torch.cuda.graph(graph):
                step_sums += self._step(index)
            self._graph = (graph, index, step_sums)
        graph, index, step_sums = self._graph
        if len(order) % batch:
            order = torch.cat([order, order[:batch - len(order) % batch]])
        step_sums.zero_()
        for start in range(0, len(order), batch):
            index.copy_(order[start:start + batch])
            graph.replay()
        sums += step_sums

    def _snapshot_every(self) -> int:
        """Epochs between weight snapshots: every epoch, or enough epochs to hold 16 steps (short CUDA epochs)."""
        return max(1, math.ceil(16 / math.ceil(len(self.data.images) / self._texels_per_step())))

    def _snapshot(self) -> dict:
        return {"model": {k: v.clone() for k, v in self.model.state_dict().items()},
                "optimizer": _clone_state(self.optimizer.state_dict())}

    def _lower_rate(self):
        for group in self.optimizer.param_groups:
            group["lr"] *= self.config.lr_drop_on_nan
        self.state.nan_recoveries += 1
        self._graph = None  # a captured step holds the old rate

    def _recover_from_nan(self, snapshot):
        """Weights that became non-finite: back to `snapshot` (the last epoch start snapshotted), at a lower rate."""
        self.model.load_state_dict(snapshot["model"])
        self.optimizer.load_state_dict(snapshot["optimizer"])  # new state tensors: a captured step is stale
        self._lower_rate()

    def train(self, progress=None, should_cancel=lambda: False, epochs: int | None = None,
              save_checkpoint: bool = True) -> TrainState:
        """Train until the time budget, a loss plateau, `epochs` more epochs, or cancellation."""
        config, state = self.config, self.state
        texels = len(self.data.images)
        batch = self._texels_per_step()
        spent = state.seconds[-1] if state.seconds else 0.0
        last_checkpoint = time.perf_counter()
        target_epoch = state.epoch + epochs if epochs is not None else config.max_epochs
        state.stopped_because = ""
        while state.epoch < target_epoch:
            if should_cancel():
                state.stopped_because = "cancelled"
                break
            if spent >= config.time_budget_s:
                state.stopped_because = "time budget"
                break
            plateaued = self._plateaued()
            if plateaued:
                state.stopped_because = plateaued
                break
            tick = time.perf_counter()
            if self.device.type == "cpu":
                order = torch.randperm(texels, generator=self.generator)
            else:  # drawn on the device: a copy from the host would wait for the device's queue
                order = torch.randperm(texels, device=self.device)
            if self._last_snapshot is None or state.epoch % self._snapshot_every() == 0:
                # a finite step can still leave non-finite weights (rare): the snapshot is what comes back then
                self._last_snapshot = self._snapshot()
            sums = torch.zeros(3, device=self.device)  # loss x texels, texels and steps skipped, on the device
            if self._uses_graph():
                try:
                    self._graph_epoch(order, batch, sums)
                except RuntimeError as error:  # a CUDA graph this torch cannot capture: the eager steps instead
                    self.graph_error = f"CUDA graph capture failed ({error}); eager steps instead"
                    self._graph = None
                    torch.cuda.synchronize(self.device)
                    sums.zero_()
                    self._eager_epoch(order, batch, sums)
            else:
                self._eager_epoch(order, batch, sums)
            weights = torch.nn.utils.get_total_norm([p.detach() for p in self.model.parameters()], norm_type=1.0)
            total, count, skipped, finite = torch.cat([sums, torch.isfinite(weights).float()[None]]).tolist()
            for _ in range(int(skipped)):  # one host synchronisation an epoch, above
                self._lower_rate()
            if not finite:
                self._recover_from_nan(self._last_snapshot)
                total, count = 0.0, 0
            spent += time.perf_counter() - tick
            state.epoch += 1
            # an epoch without a kept step repeats the last loss (0 would read as converged)
            state.losses.append(float(total) / count if count else (state.losses[-1] if state.losses else 0.0))
            state.seconds.append(spent)
            if progress is not None:
                eta = None
                if epochs is not None:
                    eta = (target_epoch - state.epoch) * spent / max(state.epoch, 1)
                progress(state.epoch, state.losses[-1], min(spent / config.time_budget_s, 1.0), eta)
            if (self.checkpoint is not None and save_checkpoint
                    and time.perf_counter() - last_checkpoint > config.checkpoint_every_s):
                self.save(self.checkpoint)
                last_checkpoint = time.perf_counter()
        else:
            state.stopped_because = "epochs"
        if self.checkpoint is not None and save_checkpoint:
            self.save(self.checkpoint)
        return state

    def _plateaued(self) -> str:
        """Why the loss has levelled off ("plateau", "little left to gain in the budget"), or "" if it has not."""
        losses, seconds = self.state.losses, self.state.seconds
        steps_per_epoch = math.ceil(len(self.data.images) / self._texels_per_step())
        window = max(self.config.plateau_epochs, math.ceil(self.config.plateau_steps / steps_per_epoch))
        if len(losses) < 2 * window:
            return ""
        last, before = np.mean(losses[-window:]), np.mean(losses[-2 * window:-window])
        if last > before * (1 - self.config.plateau_rel):
            return "plateau"
        elapsed, remaining = seconds[-1] - seconds[-1 - window], self.config.time_budget_s - seconds[-1]
        if math.isfinite(remaining) and elapsed > 0 and (before - last) / elapsed * remaining < \
                self.config.plateau_budget_rel * last:
            return "little left to gain in the budget"
        return ""

    # --- checkpoints (torch.load with weights_only=True: no pickle of arbitrary objects) --------------
    def save(self, path: Path):
        _atomic_torch_save({
            "mode": self.mode, "config": asdict(self.config), "amplitude_scale": self.amplitude_scale,
            "model": self.model.state_dict(), "optimizer": self.optimizer.state_dict(),
            "generator": self.generator.get_state(), "torch_rng": torch.get_rng_state(),
            "state": asdict(self.state),
        }, Path(path))

    def _load(self, path: Path):
        data = torch.load(path, map_location=self.device, weights_only=True)
        saved = data["config"]
        if (data.get("mode") != self.mode or saved.get("sg_count") != self.config.sg_count
                or saved.get("interpolation_weight", 0.0) != self.config.interpolation_weight):
            raise ValueError(f"{path}: checkpoint of another training set-up; delete it to start afresh")
        self.amplitude_scale = float(data["amplitude_scale"])
        self.model.load_state_dict(data["model"])
        self.optimizer.load_state_dict(data["optimizer"])
        for group in self.optimizer.param_groups:  # a checkpoint from before the fused optimiser
            group.update(fused=True, capturable=self.device.type == "cuda")
        self.generator.set_state(data["generator"])
        torch.set_rng_state(data["torch_rng"])
        self.state = TrainState(**data["state"])


def _partner_table(pairs: torch.Tensor, texels: int):
    """Adjacency of (M, 2) pairs as (neighbour list, offset, count) per texel, both directions."""
    both = torch.cat([pairs, pairs.flip(1)]).reshape(-1, 2)
    both = both[torch.argsort(both[:, 0], stable=True)]
    counts = torch.bincount(both[:, 0], minlength=texels)
    return both[:, 1].contiguous(), torch.cumsum(counts, 0) - counts, counts


def _clone_state(state):
    if isinstance(state, torch.Tensor):
        return state.clone()
    if isinstance(state, dict):
        return {k: _clone_state(v) for k, v in state.items()}
    if isinstance(state, list):
        return [_clone_state(v) for v in state]
    return state


# --- evaluation --------------------------------------------------------------------------------------
def reconstruct(axis, sharpness, amplitude, resolution: int) -> np.ndarray:
    """SG parameters (numpy) evaluated at pixel centres -> (T, R, R, C)."""
    directions = pixel_directions(resolution)
    out = []
    for start in range(0, len(axis), 512):
        a, s, m = (np.asarray(x[start:start + 512], np.float64) for x in (axis, sharpness, amplitude))
        lobes = np.exp(s[:, None, None, :] * (np.einsum("rcx,tnx->trcn", directions, a) - 1.0))
        out.append(np.einsum("trcn,tnk->trck", lobes, m))
    return np.concatenate(out).astype(np.float32)


def pair_indices(texels: np.ndarray, pairs: np.ndarray):
    """Rows (a, b) of `texels` ((T, 2) atlas [row, col]) for each pair [row, col, row2, col2] (M, 4)."""
    index = {(int(r), int(c)): i for i, (r, c) in enumerate(texels)}
    a = np.array([index[(int(r), int(c))] for r, c in pairs[:, :2]], np.int64)
    b = np.array([index[(int(r), int(c))] for r, c in pairs[:, 2:]], np.int64)
    return a, b


def energy_kept(prediction, target, normals) -> float:
    """Median over lit texels and channels of the SG reconstruction's energy over the texel's upper hemisphere
    divided by the rendered light field's. Below 1 is the log-L2 loss's bias: it fits E[log(1 + L)] of noisy
    renders, which is below log(1 + E[L]) (Jensen), so sparse bright pixels (thin emitters) lose energy."""
    from ..shaders.env_visibility import above_horizon_fraction

    resolution = target.shape[1]
    weight = (exact_solid_angles(resolution).reshape(1, -1) * above_horizon_fraction(normals, resolution))
    weight = weight.reshape(-1, resolution, resolution, 1)
    rendered = (np.asarray(target, np.float64) * weight).sum((1, 2))  # (T, C)
    fitted = (np.asarray(prediction, np.float64) * weight).sum((1, 2))
    lit = rendered > 0
    return float(np.median(fitted[lit] / rendered[lit])) if lit.any() else 1.0


def error_metrics(prediction: np.ndarray, target: np.ndarray, normals: np.ndarray) -> dict:
    """Solid-angle-weighted errors over the upper hemisphere (pixel centres): log loss, RMSE log and linear."""
    resolution = target.shape[1]
    directions = pixel_directions(resolution)
    weights = exact_solid_angles(resolution)
    normals = np.asarray(normals, np.float64)
    above = (np.einsum("rcx,tx->trc", directions, normals) > 0) | (np.abs(normals).sum(-1) == 0)[:, None, None]
    w = (weights[None] * above)[..., None]
    total = w.sum() * target.shape[-1]
    log_error = (np.log1p(np.maximum(target, 0)) - np.log1p(np.maximum(prediction, 0))) ** 2
    linear_error = (target.astype(np.float64) - prediction) ** 2
    return {"loss": float((log_error * w).sum() / total), "rmse_log": float(np.sqrt((log_error * w).sum() / total)),
            "rmse": float(np.sqrt((linear_error * w).sum() / total))}


def glossy_error(prediction: np.ndarray, target: np.ndarray, normals: np.ndarray, roughness: float) -> float:
    """Relative RMSE of the reflected radiance a surface of `roughness` sees (both light fields prefiltered by its
    GGX lobe, the prediction cut at the horizon as the render cuts the target), over reflection directions above
    each texel's horizon, weighted by solid angle. The error that decides how many SGs a material needs."""
    from ..shaders.env_visibility import above_horizon_fraction, glossy_prefilter

    resolution = target.shape[1]
    normals = np.asarray(normals, np.float64)
    horizon = above_horizon_fraction(normals, resolution)[..., None]  # (T, P, 1)
    flat = prediction.reshape(len(prediction), -1, prediction.shape[-1])
    predicted = glossy_prefilter(flat * horizon, resolution, roughness)
    expected = glossy_prefilter(target, resolution, roughness)
    above = normals @ pixel_directions(resolution).reshape(-1, 3).T > 0
    w = (exact_solid_angles(resolution).reshape(1, -1) * above)[..., None]
    return float(np.sqrt((w * (predicted - expected) ** 2).sum() / max((w * expected ** 2).sum(), 1e-30)))

