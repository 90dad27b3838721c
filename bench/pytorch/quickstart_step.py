#!/usr/bin/env python3
"""One training step of configs/quickstart.toml in plain PyTorch, timed.

A re-implementation of what `volux train bench --config configs/quickstart.toml --stage 1|2`
runs (volux-model, volux-train), written the way a PyTorch user would write it: nn.Module,
autograd, torch.autograd.grad(create_graph=True) for the normals and the R1 penalty, Adam,
an EMA copy. No custom ops; torch.compile only with --compile. See README.md next to this
file for what is mirrored, what is left out and why.

    torch-venv/bin/python bench/pytorch/quickstart_step.py --stage 1 --steps 5
    torch-venv/bin/python bench/pytorch/quickstart_step.py --stage 2 --steps 5
"""

import argparse
import contextlib
import copy
import ctypes
import ctypes.util
import math
import platform
import resource
import statistics
import sys
import time

import torch
import torch.nn as nn
import torch.nn.functional as F

# ----------------------------------------------------------------------------------------------
# configs/quickstart.toml with the `small` preset (volux-model/src/presets.rs, generator.rs)

Q = dict(
    batch=4,
    z_dim=128,
    w_dim=128,
    mapping_layers=8,
    mapping_lr_mul=0.01,
    neiif_width=64,
    neiif_layers=6,
    density_layer=4,
    frequencies=4,  # [model] frequencies = 4 (the preset has 10)
    head_width=64,
    lobes=4,  # light maps n = 1, 16, 32, 64
    specular_bias_init=-2.0,
    sphere_prior=10.0,
    sphere_radius=0.35,
    stratified=8,  # [model] stratified = 8 (the preset has 12)
    importance=8,  # [model] importance = 8 (the preset has 12)
    volume_resolution=32,
    output_resolution=64,
    upsampler_channels=32,
    relighting_channels=[16, 32],
    # camera (ray_sampling.rs CameraConfig defaults)
    cam_radius=2.7,
    fov_degrees=18.84,
    near=2.25,
    far=3.3,
    background=[1.0, 1.0, 1.0],  # [data] background, sRGB 1 -> linear 1
    # [train]
    lr_g=0.0022,
    lr_d=0.0025,
    beta1=0.0,
    beta2=0.99,
    r1_gamma=1.0,
    r1_interval=16,
    ema_kimg=0.5,
    ema_rampup=0.05,
    # [schedule]
    stage1_kimg=1.2,
    fade_kimg=0.6,
    # [loss]
    w_albedo=1.0,
    w_geometry=0.5,
    w_shading=0.25,
    w_photo=0.75,
    w_path=0.5,
    # Light-map sizes (width x height) the default tolerance plans for n = 1, 16, 32, 64
    # (`volux envmap preconvolve` on any 1024x512 map; the plan depends on the exponent only).
    light_maps=[(192, 96), (256, 128), (384, 192), (512, 256)],
)

# Parameter counts of the Rust model for this config. `volux model info --preset small` prints
# the preset's (10 octaves): mapping 132096, NeIIF 78983, upsampler 19171, relighting 30995,
# D_A lo 1153473, D_A hi 1183137, D_G 1153473, D_S 1183329, D_P 1183137. The quickstart's 4
# octaves shrink the NeIIF's first layer from 63 to 27 inputs: (w_dim + 1 + width) * 36 = 6948
# fewer, so NeIIF 72035 (the formula of generator.rs's test, paper_preset_on_a_subset...).
RUST_PARAMS = {
    "mapping network": 132096,
    "NeIIF": 72035,
    "upsampler": 19171,
    "relighting network": 30995,
    "generator": 254297,
    "D_A lo": 1153473,
    "D_A hi": 1183137,
    "D_G": 1153473,
    "D_S": 1183329,
    "D_P": 1183137,
}

SQRT2 = math.sqrt(2.0)


# ----------------------------------------------------------------------------------------------
# Per-phase wall time, exclusive of nested phases (volux-model/src/profile.rs does the same)


class Profiler:
    def __init__(self):
        self.times = {}
        self.stack = []

    @contextlib.contextmanager
    def span(self, name):
        start = time.perf_counter()
        self.stack.append(0.0)
        try:
            yield
        finally:
            elapsed = time.perf_counter() - start
            children = self.stack.pop()
            self.times[name] = self.times.get(name, 0.0) + elapsed - children
            if self.stack:
                self.stack[-1] += elapsed

    def take(self):
        times, self.times = self.times, {}
        return times


PROF = Profiler()

# Row labels, in the order of `volux train bench`'s table (volux-model/src/profile.rs).
MAPPING = "mapping"
FIELD = "NeIIF field + normals"
COMPOSITING = "compositing + light look-ups"
UPSAMPLER = "upsampler"
RELIGHTING = "relighting net"
G_BACKWARD = "generator backward"
G_ADAM = "generator Adam"
D_STEP = "discriminator step"
R1 = "R1 forward"
EMA = "EMA"
D_NAMES = ["D_A lo", "D_A hi", "D_G", "D_S", "D_P"]


def d_forward_label(name):
    return f"{name} forward (G phase)"


# ----------------------------------------------------------------------------------------------
# Layers (equalized.rs, modulated.rs, mapping.rs)


def lrelu(x):
    """StyleGAN2's leaky ReLU: slope 0.2, gain sqrt(2)."""
    return F.leaky_relu(x, 0.2) * SQRT2


SMOOTH_GAIN = 1.125


def smooth_lrelu(x):
    """The NeIIF's activation, gain (0.2 x + 0.8 softplus(x)) (neiif.rs)."""
    return SMOOTH_GAIN * (0.2 * x + 0.8 * F.softplus(x))


def smooth_lrelu_derivative(x):
    return SMOOTH_GAIN * (0.2 + 0.8 * torch.sigmoid(x))


class EqualizedLinear(nn.Module):
    def __init__(self, d_in, d_out, lr_mul=1.0, bias_init=0.0, bias=True):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(d_out, d_in) / lr_mul)
        self.bias = nn.Parameter(torch.full([d_out], bias_init / lr_mul)) if bias else None
        self.weight_gain = lr_mul / math.sqrt(d_in)
        self.bias_gain = lr_mul

    def forward(self, x):
        b = self.bias * self.bias_gain if self.bias is not None else None
        return F.linear(x, self.weight * self.weight_gain, b)


class EqualizedConv2d(nn.Module):
    def __init__(self, c_in, c_out, k, bias=True):
        super().__init__()
        self.weight = nn.Parameter(torch.randn(c_out, c_in, k, k))
        self.bias = nn.Parameter(torch.zeros(c_out)) if bias else None
        self.weight_gain = 1.0 / math.sqrt(c_in * k * k)
        self.k = k

    def forward(self, x, stride=1, padding=None):
        padding = self.k // 2 if padding is None else padding
        return F.conv2d(x, self.weight * self.weight_gain, self.bias, stride=stride, padding=padding)


class ModulatedLinear(nn.Module):
    """StyleGAN2 modulation / demodulation of a fully connected layer (per point or per pixel):
    each sample's weight diag(s) W^T diag(d) is built once and applied by a batched matmul."""

    def __init__(self, w_dim, d_in, d_out):
        super().__init__()
        self.affine = EqualizedLinear(w_dim, d_in, bias_init=1.0)
        self.weight = nn.Parameter(torch.randn(d_out, d_in))
        self.bias = nn.Parameter(torch.zeros(d_out))
        self.weight_gain = 1.0 / math.sqrt(d_in)

    def modulation(self, w):
        styles = self.affine(w)  # [b, in]
        wt = (self.weight * self.weight_gain).t()  # [in, out]
        demod = torch.rsqrt(styles.square() @ wt.square() + 1e-8)  # [b, out]
        return wt.unsqueeze(0) * styles.unsqueeze(2) * demod.unsqueeze(1)  # [b, in, out]

    def forward(self, x, w):
        """x: [b, n, in], w: [b, w_dim] -> [b, n, out]."""
        return torch.bmm(x, self.modulation(w)) + self.bias


class MappingNetwork(nn.Module):
    def __init__(self, z_dim, w_dim, layers, lr_mul):
        super().__init__()
        self.layers = nn.ModuleList(
            EqualizedLinear(z_dim if i == 0 else w_dim, w_dim, lr_mul=lr_mul) for i in range(layers)
        )

    def forward(self, z):
        x = z * torch.rsqrt(z.square().mean(dim=1, keepdim=True) + 1e-8)
        for layer in self.layers:
            x = lrelu(layer(x))
        return x


# ----------------------------------------------------------------------------------------------
# The NeIIF (neiif.rs, positional_encoding.rs)


def positional_encoding(x, frequencies):
    parts = [x]
    for k in range(frequencies):
        s = x * (math.pi * 2.0**k)
        parts += [torch.sin(s), torch.cos(s)]
    return torch.cat(parts, dim=-1)


def positional_encoding_with_derivative(x, frequencies):
    """The encoding and its diagonal derivative (column c is d enc_c / d x_{c mod 3})."""
    parts, derivs = [x], [torch.ones_like(x)]
    for k in range(frequencies):
        f = math.pi * 2.0**k
        s = x * f
        sin, cos = torch.sin(s), torch.cos(s)
        parts += [sin, cos]
        derivs += [cos * f, sin * -f]
    return torch.cat(parts, dim=-1), torch.cat(derivs, dim=-1)


class Neiif(nn.Module):
    def __init__(self, q, normals_mode):
        super().__init__()
        d = 3 + 6 * q["frequencies"]
        width = q["neiif_width"]
        self.frequencies = q["frequencies"]
        self.density_layer = q["density_layer"]
        self.prior = (q["sphere_prior"], q["sphere_radius"])
        self.normals_mode = normals_mode
        self.layers = nn.ModuleList(
            ModulatedLinear(q["w_dim"], d if i == 0 else width, width) for i in range(q["neiif_layers"])
        )
        self.density_head = EqualizedLinear(width, 1)
        self.head_hidden = EqualizedLinear(width, q["head_width"])
        self.head_out = EqualizedLinear(q["head_width"], 3 + q["lobes"])
        with torch.no_grad():  # albedo logits start at 0, specular logits at -2
            self.head_out.bias[3:] = q["specular_bias_init"]
        self.register_buffer("coordinate_masks", self._masks(d), persistent=False)

    @staticmethod
    def _masks(d):
        return torch.stack([(torch.arange(d) % 3 == j).float() for j in range(3)])  # [3, d]

    def _prior(self, points):
        """The sphere prior's logit s (r - |x|), [b, p], and its gradient -s x / |x|, [b, p, 3]."""
        s, r = self.prior
        norm = torch.sqrt(points.square().sum(-1) + 1e-12)
        return s * (r - norm), (points / norm.unsqueeze(-1)) * -s

    def _head(self, h):
        head = self.head_out(smooth_lrelu(self.head_hidden(h)))
        albedo = torch.sigmoid(head[..., :3])
        specular = F.softplus(head[..., 3:])
        return albedo, specular, h

    def forward(self, points, w):
        """points: [b, p, 3], w: [b, w_dim] -> sigma [b, p], normals, albedo [b, p, 3],
        specular weights [b, p, lobes], features [b, p, width]."""
        if self.normals_mode == "tangents":
            return self.forward_tangents(points, w)
        return self.forward_autograd(points, w)

    def forward_autograd(self, points, w):
        """The plain way: sigma's gradient with respect to the points by torch.autograd.grad
        with create_graph=True, so that a loss on the normals is differentiated twice."""
        points = points.detach().requires_grad_(True)
        s, r = self.prior
        logit = s * (r - torch.sqrt(points.square().sum(-1) + 1e-12))
        h = positional_encoding(points, self.frequencies)
        sigma = normals = None
        for i, layer in enumerate(self.layers):
            h = smooth_lrelu(layer(h, w))
            if i + 1 == self.density_layer:
                raw = self.density_head(h).squeeze(-1) + logit
                sigma = F.softplus(raw)
                (grad,) = torch.autograd.grad(sigma.sum(), points, create_graph=True)
                normals = -grad * torch.rsqrt(grad.square().sum(-1, keepdim=True) + 1e-12)
        return (sigma, normals) + self._head(h)

    def forward_tangents(self, points, w):
        """What volux does (neiif.rs): the three tangents d/dx_j pushed forward through layers
        1-4 stacked under the values, [b, 4p, width], one batched matmul per layer; first-order
        autograd then differentiates the normals."""
        b, p, _ = points.shape
        logit, prior_grad = self._prior(points)
        enc, deriv = positional_encoding_with_derivative(points, self.frequencies)  # [b, p, d]
        d = enc.shape[-1]
        t = deriv.unsqueeze(1) * self.coordinate_masks.view(1, 3, 1, d)  # [b, 3, p, d]
        h = torch.cat([enc, t.reshape(b, 3 * p, d)], dim=1)
        tangents = 3
        sigma = normals = None
        for i, layer in enumerate(self.layers):
            y = torch.bmm(h, layer.modulation(w))  # tangents share the weight, not the bias
            z = y[:, :p] + layer.bias
            if tangents:
                t = y[:, p:].reshape(b, tangents, p, -1) * smooth_lrelu_derivative(z).unsqueeze(1)
                h = torch.cat([smooth_lrelu(z), t.reshape(b, tangents * p, -1)], dim=1)
            else:
                h = smooth_lrelu(z)
            if i + 1 == self.density_layer:
                head = self.density_head
                y = (h @ (head.weight * head.weight_gain).t()).squeeze(-1)  # [b, 4p]
                raw = y[:, :p] + head.bias * head.bias_gain + logit
                sigma = F.softplus(raw)
                g = y[:, p:].reshape(b, 3, p) + prior_grad.transpose(1, 2)
                g = (g * torch.sigmoid(raw).unsqueeze(1)).transpose(1, 2)  # [b, p, 3]
                normals = -g * torch.rsqrt(g.square().sum(-1, keepdim=True) + 1e-12)
                h = h[:, :p]
                tangents = 0
        return (sigma, normals) + self._head(h)


# ----------------------------------------------------------------------------------------------
# Rays, sampling, compositing, light look-ups (ray_sampling.rs, ray_marching.rs,
# volume_rendering.rs, shading.rs, light_lookup.rs)


def camera_rays(poses, side, q):
    """poses: [b, 2] (yaw, pitch) -> origins, unit dirs [b, side^2, 3], camera basis [b, 3, 3]
    (columns right, up, back: n @ basis is n in camera space)."""
    poses = poses.double()
    yaw, pitch = poses[:, 0], poses[:, 1]
    pos = q["cam_radius"] * torch.stack(
        [torch.sin(yaw) * torch.cos(pitch), torch.sin(pitch), torch.cos(yaw) * torch.cos(pitch)], -1
    )
    back = F.normalize(pos, dim=-1)
    forward = -back
    world_up = torch.tensor([0.0, 1.0, 0.0], dtype=poses.dtype).expand_as(forward)
    right = F.normalize(torch.linalg.cross(forward, world_up), dim=-1)
    up = torch.linalg.cross(right, forward)
    tan = math.tan(math.radians(q["fov_degrees"]) / 2)
    centres = (torch.arange(side, dtype=poses.dtype) + 0.5) / side
    sx = (2 * centres - 1) * tan
    sy = (1 - 2 * centres) * tan
    dirs = (
        forward[:, None, None, :]
        + sx[None, None, :, None] * right[:, None, None, :]
        + sy[None, :, None, None] * up[:, None, None, :]
    )
    dirs = F.normalize(dirs, dim=-1).reshape(len(poses), side * side, 3)
    origins = pos[:, None, :].expand_as(dirs)
    basis = torch.stack([right, up, back], dim=-1)
    return origins.float(), dirs.float(), basis.float()


def stratified_samples(rays, samples, q, jitter=True):
    near, far = q["near"], q["far"]
    bin_ = (far - near) / samples
    starts = near + torch.arange(samples, dtype=torch.float32) * bin_
    offset = torch.rand(rays, samples) if jitter else torch.full((rays, samples), 0.5)
    return starts + offset * bin_


def segment_lengths(t, far):
    return torch.cat([t[:, 1:], torch.full_like(t[:, :1], far)], dim=1) - t


def compositing_weights(sigma, delta):
    """w_i = T_i (1 - exp(-sigma_i delta_i)), T_i from an exclusive cumulative sum."""
    tau = sigma * delta
    exclusive = torch.cat([torch.zeros_like(tau[:, :1]), torch.cumsum(tau, 1)[:, :-1]], dim=1)
    return torch.exp(-exclusive) * (1 - torch.exp(-tau))


@torch.no_grad()
def importance_samples(t, weights, count, q, jitter=True):
    """NeRF's hierarchical sampling from the coarse weights on bins between midpoints, with 1%
    of the uniform density mixed in; inverse transform of stratified uniforms."""
    rays, _ = t.shape
    near = torch.full_like(t[:, :1], q["near"])
    far = torch.full_like(t[:, :1], q["far"])
    edges = torch.cat([near, (t[:, :-1] + t[:, 1:]) / 2, far], dim=1)
    widths = edges[:, 1:] - edges[:, :-1]
    mix = 1e-2
    prob = weights / (weights.sum(1, keepdim=True) + 1e-12) * (1 - mix) + widths / (q["far"] - q["near"]) * mix
    cdf = torch.cat([torch.zeros_like(prob[:, :1]), torch.cumsum(prob, 1)], dim=1)
    starts = torch.arange(count, dtype=torch.float32) / count
    offset = torch.rand(rays, count) if jitter else torch.full((rays, count), 0.5)
    u = (starts + offset / count) * cdf[:, -1:]
    index = torch.searchsorted(cdf[:, 1:-1].contiguous(), u.contiguous(), right=True)
    frac = ((u - cdf.gather(1, index)) / (prob.gather(1, index) + 1e-12)).clamp(0, 1)
    return edges.gather(1, index) + frac * widths.gather(1, index)


def directions_to_uv(dirs, yaw):
    """Equirectangular (u, v) of directions [b, n, 3] in environments rotated by yaw [b]."""
    x, y, z = dirs.unbind(-1)
    r2 = x * x + z * z
    axis = r2 < 1e-12
    phi = torch.atan2(x.masked_fill(axis, 0.0), z.masked_fill(axis, 1.0))
    u = (phi + math.pi) / (2 * math.pi) - yaw[:, None] / (2 * math.pi)
    u = u - torch.floor(u).detach()
    v = torch.atan2(torch.sqrt(r2 + 1e-12), y) / math.pi
    return u, v


def lookup_uv(padded, u, v):
    """Bilinear look-up into padded light maps [b, 3, H + 2, W + 2] -> [b, n, 3]."""
    b, _, hp, wp = padded.shape
    w, h = wp - 2, hp - 2
    gx = (u * w + 0.5) * (2.0 / (w + 1)) - 1
    gy = (v * h + 0.5) * (2.0 / (h + 1)) - 1
    grid = torch.stack([gx, gy], dim=-1).unsqueeze(2)  # [b, n, 1, 2]
    out = F.grid_sample(padded, grid, mode="bilinear", padding_mode="border", align_corners=True)
    return out.squeeze(-1).transpose(1, 2)


def shade(light_maps, yaw, n, dirs, omega):
    """D = L_1(n), S = sum_i omega_i L_{n_i}(r), r = d - 2 (d.n) n; all [b, points, ..]."""
    reflected = dirs - 2 * (dirs * n).sum(-1, keepdim=True) * n
    diffuse = lookup_uv(light_maps[0], *directions_to_uv(n, yaw))
    u, v = directions_to_uv(reflected, yaw)
    specular = sum(lookup_uv(m, u, v) * omega[..., i : i + 1] for i, m in enumerate(light_maps))
    return diffuse, specular


def render(field, w, origins, dirs, lighting, shading, q):
    """EG3D's two passes (stratified, then importance from their weights), both through the
    full field, merged by depth; the midpoint rule; every map accumulated by the samples'
    masses. Returns [b, rays, c] maps and opacity [b, rays]."""
    b, r, _ = origins.shape
    rays = b * r

    def evaluate(t):
        s = t.shape[1]
        points = origins[:, :, None, :] + dirs[:, :, None, :] * t.reshape(b, r, s, 1)
        with PROF.span(FIELD):
            out = field(points.reshape(b, r * s, 3), w)
        sigma = out[0].reshape(rays, s)
        return [t, sigma] + [x.reshape(rays, s, -1) for x in out[1:]]

    coarse = evaluate(stratified_samples(rays, q["stratified"], q))
    with torch.no_grad():
        wc = compositing_weights(coarse[1], segment_lengths(coarse[0], q["far"]))
        t_fine = importance_samples(coarse[0], wc, q["importance"], q)
    fine = evaluate(t_fine)
    t, order = torch.sort(torch.cat([coarse[0], fine[0]], dim=1), dim=1)
    sigma = torch.cat([coarse[1], fine[1]], dim=1).gather(1, order)
    normals, albedo, omega, features = (
        torch.cat([a, c], dim=1).gather(1, order.unsqueeze(-1).expand(-1, -1, a.shape[-1]))
        for a, c in zip(coarse[2:], fine[2:])
    )
    s = t.shape[1]
    # Midpoint rule: segment i carries the mean of its ends; each sample half of each segment.
    wts = compositing_weights((sigma[:, :-1] + sigma[:, 1:]) / 2, t[:, 1:] - t[:, :-1])
    zero = torch.zeros_like(wts[:, :1])
    mass = (torch.cat([zero, wts], 1) + torch.cat([wts, zero], 1)) / 2

    def acc(x):
        return (x * mass.unsqueeze(-1)).sum(1).reshape(b, r, -1)

    out = dict(
        opacity=wts.sum(1).reshape(b, r),
        albedo=acc(albedo),
        normals=acc(normals),
        features=acc(features),
    )
    if shading:
        maps, yaw = lighting
        d = dirs[:, :, None, :].expand(b, r, s, 3).reshape(b, r * s, 3)
        dif, spec = shade(maps, yaw, normals.reshape(b, r * s, 3), d, omega.reshape(b, r * s, -1))
        out["diffuse"] = acc(dif.reshape(rays, s, 3))
        out["specular"] = acc(spec.reshape(rays, s, 3))
    return out


# ----------------------------------------------------------------------------------------------
# Upsampler and relighting U-Net (upsampler.rs, relighting.rs)


def bilinear_up(x, f=2):
    return F.interpolate(x, scale_factor=f, mode="bilinear", align_corners=False)


def area_down(x, f):
    return F.avg_pool2d(x, f) if f > 1 else x


_BLURPOOL = torch.outer(torch.tensor([1.0, 2.0, 1.0]), torch.tensor([1.0, 2.0, 1.0])) / 16


def blur_stride1(x):
    """BlurPool with stride 1: [1, 2, 1] x [1, 2, 1] / 16 per channel, edges replicated."""
    c = x.shape[1]
    return F.conv2d(F.pad(x, (1, 1, 1, 1), mode="replicate"), _BLURPOOL.expand(c, 1, 3, 3), groups=c)


def conv1x1(layer, x, w):
    b, c, h, wd = x.shape
    y = layer(x.reshape(b, c, h * wd).transpose(1, 2), w)
    return y.transpose(1, 2).reshape(b, -1, h, wd)


class Upsampler(nn.Module):
    def __init__(self, w_dim, c_in, channels, blocks):
        super().__init__()
        self.blocks = nn.ModuleList(
            nn.ModuleDict(
                dict(
                    conv1=ModulatedLinear(w_dim, c_in if i == 0 else channels, channels),
                    conv2=ModulatedLinear(w_dim, channels, 4 * channels),
                )
            )
            for i in range(blocks)
        )

    def forward(self, x, w, fade):
        for i, block in enumerate(self.blocks):
            albedo = bilinear_up(x[:, :3])
            h = smooth_lrelu(conv1x1(block["conv1"], x, w))
            y = blur_stride1(F.pixel_shuffle(conv1x1(block["conv2"], h, w), 2))
            alpha = 1.0 if fade is None else fade[i]
            x = torch.cat([albedo + y[:, :3] * alpha, y[:, 3:]], dim=1)
        return x


def tonemap_srgb(x):
    x = x.clamp_min(0)
    lum = 0.2126 * x[:, 0:1] + 0.7152 * x[:, 1:2] + 0.0722 * x[:, 2:3]
    y = (x / (lum + 1)).clamp_max(1)
    curve = 1.055 * y.clamp_min(0.0031308).pow(1 / 2.4) - 0.055
    return torch.where(y <= 0.0031308, 12.92 * y, curve)


class ConvPair(nn.Module):
    def __init__(self, c_in, c_out):
        super().__init__()
        self.a = EqualizedConv2d(c_in, c_out, 3)
        self.b = EqualizedConv2d(c_out, c_out, 3)

    def forward(self, x):
        return lrelu(self.b(lrelu(self.a(x))))


class RelightingNet(nn.Module):
    def __init__(self, feature_channels, channels):
        super().__init__()
        self.down = nn.ModuleList()
        c_in = 9 + feature_channels
        for c in channels:
            self.down.append(ConvPair(c_in, c))
            c_in = c
        self.up = nn.ModuleList()
        for level in reversed(range(len(channels) - 1)):
            self.up.append(ConvPair(c_in + channels[level], channels[level]))
            c_in = channels[level]
        self.out = EqualizedConv2d(c_in, 3, 1)
        nn.init.zeros_(self.out.weight)

    def forward(self, albedo, diffuse, specular, features):
        phong = tonemap_srgb(albedo * diffuse + specular) * 2 - 1
        x = torch.cat(
            [albedo * 2 - 1, diffuse.clamp_min(0).log1p(), specular.clamp_min(0).log1p(), features], dim=1
        )
        skips = []
        for i, level in enumerate(self.down):
            x = level(F.avg_pool2d(x, 2) if i > 0 else x)
            skips.append(x)
        skips.pop()
        for level in self.up:
            x = level(torch.cat([bilinear_up(x), skips.pop()], dim=1))
        return phong + self.out(x)


# ----------------------------------------------------------------------------------------------
# The generator (generator.rs)


class Generator(nn.Module):
    def __init__(self, q, normals_mode):
        super().__init__()
        self.q = q
        self.mapping = MappingNetwork(q["z_dim"], q["w_dim"], q["mapping_layers"], q["mapping_lr_mul"])
        self.neiif = Neiif(q, normals_mode)
        blocks = int(math.log2(q["output_resolution"] // q["volume_resolution"]))
        self.upsampler = Upsampler(q["w_dim"], 3 + q["neiif_width"], q["upsampler_channels"], blocks)
        self.relighting = RelightingNet(q["upsampler_channels"] - 3, q["relighting_channels"])
        # What forward calls; --compile swaps in compiled versions (a plain dict, so that the
        # aliases are not registered as submodules).
        self.run = dict(mapping=self.mapping, field=self.neiif, upsampler=self.upsampler, relighting=self.relighting)

    def parameter_counts(self):
        count = lambda m: sum(p.numel() for p in m.parameters())
        return {
            "mapping network": count(self.mapping),
            "NeIIF": count(self.neiif),
            "upsampler": count(self.upsampler),
            "relighting network": count(self.relighting),
            "generator": count(self),
        }

    def forward(self, z, poses, lighting, fade, relit):
        """Stage 1 (relit=False): A_lo, N_lo, A_hi. Stage 2: also D_lo, S_lo and I_relit."""
        q = self.q
        side = q["volume_resolution"]
        b = z.shape[0]
        with PROF.span(MAPPING):
            w = self.run["mapping"](z)
        with PROF.span(COMPOSITING):
            origins, dirs, basis = camera_rays(poses, side, q)
            r = render(self.run["field"], w, origins, dirs, lighting, relit, q)

            def image(x):
                return x.transpose(1, 2).reshape(b, -1, side, side)

            opacity = image(r["opacity"].unsqueeze(-1))
            bg = torch.tensor(q["background"]).view(1, 3, 1, 1)
            out = dict(
                albedo_lo=image(r["albedo"]) + (1 - opacity) * bg,
                normals_lo=image(torch.bmm(r["normals"], basis)),  # camera space
            )
            features_lo = image(r["features"])
            if relit:
                out["diffuse_lo"] = image(r["diffuse"])
                out["specular_lo"] = image(r["specular"])
        with PROF.span(UPSAMPLER):
            hi = self.run["upsampler"](torch.cat([out["albedo_lo"], features_lo], dim=1), w, fade)
        out["albedo_hi"] = hi[:, :3]
        if relit:
            with PROF.span(RELIGHTING):
                f = q["output_resolution"] // side
                d_up = bilinear_up(out["diffuse_lo"], f)
                s_up = bilinear_up(out["specular_lo"], f)
                out["relit"] = self.run["relighting"](hi[:, :3], d_up, s_up, hi[:, 3:])
        return out


# ----------------------------------------------------------------------------------------------
# StyleGAN2's residual discriminator (discriminator.rs, blur.rs), DiscriminatorConfig::small

_FIR = torch.outer(torch.tensor([1.0, 3.0, 3.0, 1.0]), torch.tensor([1.0, 3.0, 3.0, 1.0])) / 64


def blur(x, padding, stride):
    c = x.shape[1]
    return F.conv2d(x, _FIR.expand(c, 1, 4, 4), stride=stride, padding=padding, groups=c)


class DiscriminatorBlock(nn.Module):
    def __init__(self, c_in, c_out):
        super().__init__()
        self.conv0 = EqualizedConv2d(c_in, c_in, 3)
        self.conv1 = EqualizedConv2d(c_in, c_out, 3)
        self.skip = EqualizedConv2d(c_in, c_out, 1, bias=False)

    def forward(self, x):
        skip = self.skip(blur(x, 1, 2), padding=0)
        x = lrelu(self.conv0(x))
        x = lrelu(self.conv1(blur(x, 2, 1), stride=2, padding=0))
        return (skip + x) / SQRT2


def minibatch_std(x, group=4, features=1):
    n, c, h, w = x.shape
    g = min(group, n)
    y = x.reshape(g, -1, features, c // features, h, w)
    y = (y - y.mean(0)).square().mean(0).add(1e-8).sqrt()
    y = y.mean(dim=[2, 3, 4]).reshape(-1, features, 1, 1).repeat(g, 1, h, w)
    return torch.cat([x, y], dim=1)


class Discriminator(nn.Module):
    def __init__(self, in_channels, resolution, channel_base=2048, channel_max=128):
        super().__init__()
        ch = lambda r: max(1, min(channel_base // r, channel_max))
        self.from_rgb = EqualizedConv2d(in_channels, ch(resolution), 1)
        blocks, r = [], resolution
        while r > 4:
            blocks.append(DiscriminatorBlock(ch(r), ch(r // 2)))
            r //= 2
        self.blocks = nn.ModuleList(blocks)
        c4 = ch(4)
        self.conv = EqualizedConv2d(c4 + 1, c4, 3)
        self.fc = EqualizedLinear(c4 * 16, c4)
        self.out = EqualizedLinear(c4, 1)

    def forward(self, x):
        x = lrelu(self.from_rgb(x))
        for block in self.blocks:
            x = block(x)
        x = lrelu(self.conv(minibatch_std(x)))
        return self.out(lrelu(self.fc(x.flatten(1))))


def make_discriminators(q):
    lo, hi = q["volume_resolution"], q["output_resolution"]
    return nn.ModuleDict(
        {
            "D_A lo": Discriminator(3, lo),
            "D_A hi": Discriminator(3, hi),
            "D_G": Discriminator(3, lo),
            "D_S": Discriminator(9, hi),
            "D_P": Discriminator(3, hi),
        }
    )


# ----------------------------------------------------------------------------------------------
# Losses, schedule, the step (losses.rs, progressive.rs, schedule.rs, step.rs, networks.rs)


def faded_input(x, fade):
    """What the high-resolution D_A sees while the upsampler fades in (progressive.rs)."""
    if fade is None or all(a >= 1 for a in fade):
        return x
    n = len(fade)
    r = area_down(x, 2**n)
    for k, alpha in enumerate(fade):
        up, target = bilinear_up(r), area_down(x, 2 ** (n - k - 1))
        r = target if alpha >= 1 else up if alpha <= 0 else up + (target - up) * alpha
    return r


def shading_condition_lo(relit, diffuse_lo, specular_lo):
    """D_S's input: [I_relit, log1p(D_up), log1p(S_up)], shading detached."""
    f = relit.shape[2] // diffuse_lo.shape[2]
    d = bilinear_up(diffuse_lo.detach(), f)
    s = bilinear_up(specular_lo.detach(), f)
    return torch.cat([relit, d.log1p(), s.log1p()], dim=1)


def ema_beta(batch, images, ema_kimg, rampup):
    half_life = ema_kimg * 1000.0
    if rampup > 0:
        half_life = min(half_life, images * rampup)
    return 0.0 if half_life <= 0 else 0.5 ** (batch / half_life)


def all_finite(params):
    return bool(torch.isfinite(torch.stack([p.detach().sum() for p in params]).sum()))


class Trainer:
    def __init__(self, args, q):
        self.q = q
        self.stage = args.stage
        self.G = Generator(q, args.normals)
        self.D = make_discriminators(q)
        self.G_ema = copy.deepcopy(self.G).eval().requires_grad_(False)
        betas = (q["beta1"], q["beta2"])
        self.opt_g = torch.optim.Adam(self.G.parameters(), lr=q["lr_g"], betas=betas, eps=1e-8)
        self.opt_d = torch.optim.Adam(self.D.parameters(), lr=q["lr_d"], betas=betas, eps=1e-8)
        # The bench places every step at the stage's first image (bench.rs, Trainer::seek).
        self.images = 0 if args.stage == 1 else round(q["stage1_kimg"] * 1000)
        blocks = len(self.G.upsampler.blocks)
        kimg = self.images / 1000
        self.fade = (
            [min(max((kimg - i * q["fade_kimg"]) / q["fade_kimg"], 0.0), 1.0) for i in range(blocks)]
            if args.stage == 1
            else None
        )
        self.active = ["D_A lo", "D_A hi", "D_G"] + (["D_S", "D_P"] if args.stage == 2 else [])
        self.weights = {
            "D_A lo": q["w_albedo"],
            "D_A hi": q["w_albedo"],
            "D_G": q["w_geometry"],
            "D_S": q["w_shading"],
            "D_P": q["w_photo"],
        }
        # Discriminator forwards without R1; --compile replaces these, R1 always runs eagerly
        # (torch.compile does not support double backward).
        self.d_run = {name: self.D[name] for name in D_NAMES}
        if args.compile:
            self.compile(args)
        self.skipped = 0

    def compile(self, args):
        # The upsampler stays eager: PyTorch 2.15's inductor fails a stride assertion in the
        # backward of its replicate padding (replication_pad2d_backward).
        run = self.G.run
        for part in ["mapping", "relighting"]:
            run[part] = torch.compile(run[part])
        if args.normals == "tangents":  # autograd normals are differentiated twice: eager
            run["field"] = torch.compile(run["field"])
        self.d_run = {name: torch.compile(self.D[name]) for name in D_NAMES}

    def pairs(self, fakes, reals):
        """(name, fake, real) for every active discriminator, as it sees them."""
        f, r = fakes, reals
        out = {
            "D_A lo": (f["albedo_lo"], r and r["albedo_lo"]),
            "D_A hi": (faded_input(f["albedo_hi"], self.fade), r and faded_input(r["albedo_hi"], self.fade)),
            "D_G": (f["normals_lo"], r and r["normals_lo"]),
        }
        if self.stage == 2:
            real_shading = r and shading_condition_lo(
                r["relit"], area_down(r["diffuse"], 2), area_down(r["specular"], 2)
            )
            out["D_S"] = (f["shading"], real_shading)
            out["D_P"] = (f["relit"], r and r["photo"])
        return [(name,) + out[name] for name in self.active]

    def step(self, z, poses, lighting, reals, run_r1):
        q, losses = self.q, {}
        relit = self.stage == 2

        # Generator phase: the discriminators are frozen.
        self.D.requires_grad_(False)
        out = self.G(z, poses, lighting, self.fade, relit)
        path = (out["albedo_lo"] - area_down(out["albedo_hi"], 2)).abs().mean()
        fakes = dict(out)
        if relit:
            fakes["shading"] = shading_condition_lo(out["relit"], out["diffuse_lo"], out["specular_lo"])
        g_loss = path * q["w_path"]
        losses["path"] = path.item()
        for name, fake, _ in self.pairs(fakes, None):
            with PROF.span(d_forward_label(name)):
                logits = self.d_run[name](fake)
            term = F.softplus(-logits).mean()
            losses["G " + name] = term.item()
            g_loss = g_loss + term * self.weights[name]
        losses["G total"] = g_loss.item()
        if not math.isfinite(losses["G total"]):
            self.skipped += 1
            self.D.requires_grad_(True)
            return losses
        self.opt_g.zero_grad(set_to_none=True)
        with PROF.span(G_BACKWARD):
            g_loss.backward()
        with PROF.span(G_ADAM):
            self.opt_g.step()
            if not all_finite(self.G.parameters()):
                self.skipped += 1  # volux restores the weights here (see README)

        # Discriminator phase on the same fakes, detached; lazy R1 on reals.
        self.D.requires_grad_(True)
        with PROF.span(D_STEP):
            fakes = {k: v.detach() for k, v in fakes.items()}
            d_loss = 0.0
            for name, fake, real in self.pairs(fakes, reals):
                if run_r1:
                    with PROF.span(R1):
                        real = real.detach().requires_grad_(True)
                        real_logits = self.D[name](real)
                        (grad,) = torch.autograd.grad(real_logits.sum(), real, create_graph=True)
                        r1 = grad.square().sum(dim=[1, 2, 3]).mean() * (q["r1_gamma"] / 2) * q["r1_interval"]
                    losses["R1 " + name] = r1.item()
                else:
                    real_logits, r1 = self.d_run[name](real), 0.0
                term = F.softplus(self.d_run[name](fake)).mean() + F.softplus(-real_logits).mean()
                losses["D " + name] = term.item()
                d_loss = d_loss + (term + r1) * self.weights[name]
            losses["D total"] = d_loss.item()
            if not math.isfinite(losses["D total"]):
                self.skipped += 1
                return losses
            self.opt_d.zero_grad(set_to_none=True)
            d_loss.backward()
            self.opt_d.step()
            if not all_finite(self.D.parameters()):
                self.skipped += 1

        with PROF.span(EMA), torch.no_grad():
            beta = ema_beta(q["batch"], self.images + q["batch"], q["ema_kimg"], q["ema_rampup"])
            for p_ema, p in zip(self.G_ema.parameters(), self.G.parameters()):
                p_ema.lerp_(p, 1 - beta)
        return losses


# ----------------------------------------------------------------------------------------------
# Inputs (random, made once, outside the timed region) and the benchmark


def make_inputs(q, stage):
    b, hi, lo = q["batch"], q["output_resolution"], q["volume_resolution"]
    rand = lambda c, s: torch.rand(b, c, s, s)
    reals = dict(
        photo=rand(3, hi) * 2 - 1,
        relit=rand(3, hi) * 2 - 1,
        albedo_hi=rand(3, hi),
        albedo_lo=rand(3, lo),
        normals_lo=F.normalize(torch.randn(b, 3, lo, lo), dim=1),
        diffuse=rand(3, hi) * 2,
        specular=rand(3, hi),
    )
    # The reals' poses (pi-GAN's prior, truncated at 3 sd); the fakes are seen from them.
    poses = torch.stack([0.3 * torch.randn(b).clamp(-3, 3), 0.155 * torch.randn(b).clamp(-3, 3)], dim=1)
    lighting = None
    if stage == 2:  # padded light maps [b, 3, H + 2, W + 2] (random HDR values) and a yaw each
        maps = [torch.rand(b, 3, h + 2, w + 2) * 4 for w, h in q["light_maps"]]
        lighting = (maps, torch.rand(b) * 2 * math.pi)
    return reals, poses, lighting


def volux_malloc():
    """glibc settings of volux's binary (src/allocator.rs): freed blocks stay in the heap (no
    mmap, no trimming), so large tensors freed and allocated again every step are not
    page-faulted and zeroed by the kernel each time. Returns whether glibc took them."""
    libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    m_trim_threshold, m_mmap_max = -1, -4  # <malloc.h>
    return libc.mallopt(m_mmap_max, 0) == 1 and libc.mallopt(m_trim_threshold, 2**31 - 1) == 1


def peak_rss_mib():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # KiB on Linux


def markdown(args, q, step_times, r1_flags, phase_times, params, peak, field_label):
    median = statistics.median(step_times)
    lines = [
        f"PyTorch {torch.__version__}, `configs/quickstart.toml` (small preset), stage {args.stage}, "
        f"batch {q['batch']}, CPU, {args.threads} threads, normals by "
        f"{'forward-mode tangents' if args.normals == 'tangents' else 'torch.autograd.grad(create_graph=True)'}"
        f"{', torch.compile' if args.compile else ''}"
        f"{', volux malloc settings' if args.volux_malloc else ''}: median of {len(step_times)} steps after "
        f"{args.warmup} warm-up step(s).",
        "",
        f"- step: {median:.3f} s median, {q['batch'] / median:.2f} images/s; peak memory "
        f"{peak:.0f} MiB (process RSS, ru_maxrss)",
    ]
    with_r1 = [t for t, r in zip(step_times, r1_flags) if r]
    without = [t for t, r in zip(step_times, r1_flags) if not r]
    if with_r1 and without:
        lines.append(
            f"- steps with R1: {len(with_r1)}, median {statistics.median(with_r1):.3f} s; without: "
            f"{len(without)}, median {statistics.median(without):.3f} s"
        )
    if args.r1_every_step:
        lines.append("- R1 on every step (--r1-every-step)")
    else:
        lines.append(
            f"- R1 runs on 1 step in {q['r1_interval']} (the first measured step, as in "
            "`volux train bench`); its row is the median over the steps that ran it"
        )
    lines.append(
        "- parameters: "
        + ", ".join(f"{k} {v}" for k, v in params.items())
    )
    lines += ["", "| phase | median ms | share of step |", "|---|---|---|"]
    order = [MAPPING, FIELD, COMPOSITING, UPSAMPLER, RELIGHTING]
    order += [d_forward_label(n) for n in D_NAMES] + [G_BACKWARD, G_ADAM, D_STEP, R1, EMA]
    for name in order:
        ran = [t[name] for t in phase_times if name in t]
        if not ran:
            continue
        m = statistics.median(ran)
        label = field_label if name == FIELD else name
        lines.append(f"| {label} | {1e3 * m:.1f} | {100 * m / median:.1f}% |")
    other = [total - sum(t.values()) for total, t in zip(step_times, phase_times)]
    m = statistics.median(other)
    lines.append(f"| other (losses, .item(), detach, shading condition) | {1e3 * m:.1f} | {100 * m / median:.1f}% |")
    lines.append(f"| **whole step** | {1e3 * median:.1f} | 100% |")
    return "\n".join(lines) + "\n"


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--stage", type=int, choices=[1, 2], default=1)
    ap.add_argument("--steps", type=int, default=5, help="measured steps (default 5)")
    ap.add_argument("--warmup", type=int, default=1, help="warm-up steps, not measured (default 1)")
    ap.add_argument("--threads", type=int, default=2, help="torch.set_num_threads (default 2)")
    ap.add_argument(
        "--normals",
        choices=["autograd", "tangents"],
        default="autograd",
        help="autograd: torch.autograd.grad(sigma, points, create_graph=True) (default); "
        "tangents: volux's forward-mode tangents stacked under the values",
    )
    ap.add_argument("--r1-every-step", action="store_true", help="run R1 on every step")
    ap.add_argument("--compile", action="store_true", help="torch.compile what is differentiated once")
    ap.add_argument(
        "--volux-malloc",
        action="store_true",
        help="glibc's allocator set as volux's binary sets it (mallopt: no mmap, no trimming)",
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="also write the markdown table to this file")
    args = ap.parse_args()
    if args.steps < 1:
        ap.error("--steps must be at least 1")

    if args.volux_malloc and not volux_malloc():
        print("warning: glibc refused the mallopt settings", file=sys.stderr)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    q = Q
    trainer = Trainer(args, q)

    params = trainer.G.parameter_counts()
    params.update({name: sum(p.numel() for p in trainer.D[name].parameters()) for name in D_NAMES})
    print(f"PyTorch {torch.__version__}, Python {platform.python_version()}, {args.threads} threads")
    print(f"{'parameters':<22}{'PyTorch':>10}{'volux':>10}")
    for name, n in params.items():
        want = RUST_PARAMS[name]
        print(f"  {name:<20}{n:>10}{want:>10}  {'same' if n == want else 'DIFFERENT'}")

    reals, poses, lighting = make_inputs(q, args.stage)
    z_all = torch.randn(args.warmup + args.steps, q["batch"], q["z_dim"])
    interval = q["r1_interval"]
    # Step numbers as `volux train bench` takes them: warm-up from step 0 (which runs R1), the
    # measured steps from the next multiple of r1_interval, so that the first of them runs R1.
    first = -(-max(args.warmup, interval) // interval) * interval if interval > 0 else args.warmup
    numbers = list(range(args.warmup)) + [first + i for i in range(args.steps)]

    step_times, r1_flags, phase_times = [], [], []
    for i, number in enumerate(numbers):
        run_r1 = args.r1_every_step or (interval > 0 and number % interval == 0)
        PROF.take()
        before = resource.getrusage(resource.RUSAGE_SELF)
        started = time.perf_counter()
        trainer.step(z_all[i], poses, lighting, reals, run_r1)
        seconds = time.perf_counter() - started
        after = resource.getrusage(resource.RUSAGE_SELF)
        times = PROF.take()
        measured = i >= args.warmup
        print(
            f"{'measured' if measured else 'warm-up'} step {number}: {seconds:.3f} s"
            f"{' (R1)' if run_r1 else ''}; CPU user {after.ru_utime - before.ru_utime:.2f} s, "
            f"system {after.ru_stime - before.ru_stime:.2f} s, "
            f"{(after.ru_minflt - before.ru_minflt) / 1e3:.0f}k minor page faults",
            flush=True,
        )
        if measured:
            step_times.append(seconds)
            r1_flags.append(run_r1)
            phase_times.append(times)
    if trainer.skipped:
        print(f"warning: {trainer.skipped} non-finite losses or weights", file=sys.stderr)

    field_label = "NeIIF field + tangents" if args.normals == "tangents" else FIELD
    table = markdown(args, q, step_times, r1_flags, phase_times, params, peak_rss_mib(), field_label)
    print()
    print(table, end="")
    if args.out:
        with open(args.out, "w") as f:
            f.write(table)


if __name__ == "__main__":
    main()
