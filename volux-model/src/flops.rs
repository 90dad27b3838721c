//! Floating-point operation counts of the networks, from their configured shapes: what a
//! training step asks of the machine, to compare with its measured peak.
//!
//! Conventions (one multiply-add is 2 FLOPs):
//!
//! | operation | FLOPs | |
//! |---|---|---|
//! | matmul `[m, k] x [k, n]` | `2 m n k` | [`matmul`] |
//! | convolution, per image | `2 C_in C_out k k H_out W_out` | [`conv2d`] |
//! | depthwise filter of `T` taps, per image | `2 C T H_out W_out` | [`depthwise`] |
//! | depthwise transposed convolution, kernel `K x K`, per image | `2 C K^2 H_in W_in` | [`bilinear_upsample`] |
//!
//! **Exact** counts ([`mapping`], [`field`], [`upsampler`], [`relighting`],
//! [`discriminator`], [`discriminator_input_gradient`]) count every matmul and convolution
//! (blurs and bilinear upsamplings included) the code runs, and no elementwise work
//! (activations, sin/cos, normalisation): on these networks the dense work dominates.
//! **Estimates**: [`compositing`] is elementwise only, so it is counted with the per-element
//! costs documented there; [`adam`] and [`ema`] likewise; backward passes are not counted
//! from shapes but taken as [`BACKWARD_FACTOR`] times the forward (the weight and input
//! gradients of a matmul or convolution each cost one forward).

use crate::discriminator::DiscriminatorConfig;
use crate::field::FieldWants;
use crate::generated::GeneratorWants;
use crate::generator::GeneratorConfig;
use crate::mapping::MappingNetworkConfig;
use crate::neiif::NeiifConfig;
use crate::positional_encoding::PositionalEncodingConfig;
use crate::relighting::RelightingConfig;
use crate::template_planes::TAPS as TEMPLATE_TAPS;
use crate::upsampler::UpsamplerConfig;

/// Backward FLOPs per forward FLOP where a backward pass is not counted from shapes: input
/// and weight gradients each cost about one forward. An estimate.
pub const BACKWARD_FACTOR: f64 = 2.0;

/// `[m, k] x [k, n]`.
pub fn matmul(m: usize, n: usize, k: usize) -> f64 {
    2.0 * m as f64 * n as f64 * k as f64
}

/// A dense convolution of one image: `c_in -> c_out`, `kernel x kernel`, output
/// `h_out x w_out`.
pub fn conv2d(c_in: usize, c_out: usize, kernel: usize, h_out: usize, w_out: usize) -> f64 {
    2.0 * (c_in * c_out * kernel * kernel) as f64 * (h_out * w_out) as f64
}

/// A depthwise filter of `taps` taps on `channels` channels of one image, output
/// `h_out x w_out`.
pub fn depthwise(channels: usize, taps: usize, h_out: usize, w_out: usize) -> f64 {
    2.0 * (channels * taps) as f64 * (h_out * w_out) as f64
}

/// The bilinear upsampling of [`crate::upsampler::bilinear_upsample`] for one image: a
/// depthwise transposed convolution with a `2f x 2f` tent on the edge-replicated input
/// `(h + 2) x (w + 2)`.
pub fn bilinear_upsample(channels: usize, h: usize, w: usize, factor: usize) -> f64 {
    if factor == 1 {
        return 0.0;
    }
    depthwise(channels, 4 * factor * factor, h + 2, w + 2)
}

/// The mapping network on a batch.
pub fn mapping(c: &MappingNetworkConfig, batch: usize) -> f64 {
    (0..c.layers)
        .map(|i| {
            let d_in = if i == 0 { c.z_dim } else { c.w_dim };
            matmul(batch, c.w_dim, d_in)
        })
        .sum()
}

/// A modulated layer's per-sample weight: the style affine and the demodulation matmul.
fn modulation(w_dim: usize, d_in: usize, d_out: usize, batch: usize) -> f64 {
    matmul(batch, d_in, w_dim) + matmul(batch, d_out, d_in)
}

/// One query of the NeIIF at `points` points of each of `batch` elements: values through
/// every layer it needs; when normals are wanted, the reverse sweep's product with each
/// transposed weight of layers 1 to the density layer (the head's weight is the sweep's
/// start, so the head costs nothing more); the head when appearance is.
pub fn field(c: &NeiifConfig, batch: usize, points: usize, wants: FieldWants) -> f64 {
    let n = batch * points;
    let template = if c.template_resolution > 0 {
        c.template_channels
    } else {
        0
    };
    let encoded = PositionalEncodingConfig::new()
        .with_frequencies(c.frequencies)
        .init()
        .output_dim()
        + template;
    let sweep = if wants.normals { 2 } else { 1 };
    // The template planes' weighted gathers: a multiply-add per tap, channel and output (the
    // features, and their three derivatives with normals); with normals, the sweep's fold
    // (a multiply-add per channel and axis).
    let (outputs, fold) = if wants.normals { (4, 6) } else { (1, 0) };
    let mut total = (n * template * (2 * TEMPLATE_TAPS * outputs + fold)) as f64;
    if template > 0 && c.template_basis > 0 {
        // Each latent's planes: its coefficients, then the basis weighted and added.
        let rows = 3 * c.template_resolution * c.template_resolution;
        total += matmul(batch, c.template_basis, c.w_dim)
            + matmul(batch, rows * template, c.template_basis);
    }
    let last = if wants.appearance {
        c.layers
    } else {
        c.density_layer
    };
    for i in 0..last {
        let d_in = if i == 0 { encoded } else { c.width };
        let copies = if i < c.density_layer { sweep } else { 1 };
        total += modulation(c.w_dim, d_in, c.width, batch);
        total += copies as f64 * matmul(n, c.width, d_in);
    }
    total += matmul(n, 1, c.width);
    if wants.appearance {
        total += matmul(n, c.head_width, c.width) + matmul(n, 3 + c.specular_lobes, c.head_width);
    }
    total
}

/// The density-only passes that place the importance samples on `rays` rays of each of
/// `batch` elements (none without `renderer.proposal`): the field up to its density head at
/// `proposal + refine` points per ray, their segment weights and the inverse-transform
/// draws.
pub fn proposal(c: &GeneratorConfig, batch: usize, rays: usize) -> f64 {
    let r = &c.renderer;
    if r.proposal == 0 {
        return 0.0;
    }
    let queried = r.density_only_samples();
    let draws = r.refine + r.importance;
    field(&c.neiif, batch, rays * queried, FieldWants::DENSITY)
        + (batch * rays) as f64
            * (queried as f64 * OPS_PER_SEGMENT + draws as f64 * OPS_PER_IMPORTANCE_SAMPLE)
}

/// Elementwise operations per compositing segment for its weight: the midpoint density and
/// length, optical depth, exclusive cumulative sum, transmittance and alpha. An estimate.
pub const OPS_PER_SEGMENT: f64 = 10.0;
/// Per segment and accumulated channel: the midpoint value, the weighting and the sum.
pub const OPS_PER_CHANNEL: f64 = 4.0;
/// Per importance sample: inverse-transform sampling of the coarse weights (CDF, search,
/// interpolation, sorting the merged depths). An estimate.
pub const OPS_PER_IMPORTANCE_SAMPLE: f64 = 20.0;
/// Per shaded sample: the reflected direction and two direction-to-`(u, v)` conversions.
pub const OPS_PER_SHADED_SAMPLE: f64 = 50.0;
/// Per shaded sample and light map: a bilinear look-up of 3 channels (indices, 4 taps,
/// weights) and the specular weighting.
pub const OPS_PER_LOOKUP: f64 = 40.0;

/// The renderer's own work on `rays` rays of each of `batch` elements with `stratified` +
/// `importance` samples, accumulating `channels` channels, with `lobes` light maps looked up
/// per sample when shading (0: none). Elementwise only: an estimate from the per-element
/// costs above.
pub fn compositing(
    batch: usize,
    rays: usize,
    stratified: usize,
    importance: usize,
    channels: usize,
    lobes: usize,
) -> f64 {
    let rays = (batch * rays) as f64;
    let samples = (stratified + importance) as f64;
    let mut per_ray = samples * (OPS_PER_SEGMENT + OPS_PER_CHANNEL * channels as f64);
    if importance > 0 {
        per_ray +=
            stratified as f64 * OPS_PER_SEGMENT + importance as f64 * OPS_PER_IMPORTANCE_SAMPLE;
    }
    if lobes > 0 {
        per_ray += samples * (OPS_PER_SHADED_SAMPLE + lobes as f64 * OPS_PER_LOOKUP);
    }
    rays * per_ray
}

/// The upsampler on a batch of `side x side` inputs: per block the albedo's bilinear x2, two
/// modulated `kernel x kernel` convolutions (a layer over each pixel's stacked neighbourhood)
/// and the stride-1 blur after the pixel shuffle.
pub fn upsampler(c: &UpsamplerConfig, batch: usize, side: usize) -> f64 {
    let mut total = 0.0;
    let mut r = side;
    let taps = c.kernel * c.kernel;
    for i in 0..c.blocks {
        let c_in = taps * if i == 0 { c.in_channels } else { c.channels };
        let pixels = batch * r * r;
        total += batch as f64 * bilinear_upsample(3, r, r, 2);
        total += modulation(c.w_dim, c_in, c.channels, batch) + matmul(pixels, c.channels, c_in);
        total += modulation(c.w_dim, taps * c.channels, 4 * c.channels, batch)
            + matmul(pixels, 4 * c.channels, taps * c.channels);
        total += batch as f64 * depthwise(c.channels, 9, 2 * r, 2 * r);
        r *= 2;
    }
    total
}

/// The upsampler's noise inputs ([`crate::upsampler_noise`]) on a batch of `side x side`
/// inputs, `octaves` per block: each block's gain layer `C -> K C` at its output resolution and
/// the strengths' and noise's products and sum (`3 K C` per pixel). The noise itself is value
/// noise drawn on the host, not counted.
pub fn upsampler_noise(c: &UpsamplerConfig, octaves: usize, batch: usize, side: usize) -> f64 {
    if octaves == 0 {
        return 0.0;
    }
    let gains = octaves * c.channels;
    (1..=c.blocks)
        .map(|i| {
            let pixels = batch * (side << i) * (side << i);
            modulation(c.w_dim, c.channels, gains, batch)
                + matmul(pixels, gains, c.channels)
                + 3.0 * (pixels * gains) as f64
        })
        .sum()
}

/// The relighting U-Net on a batch of `side x side` inputs (its two 3x3 convolutions per
/// level, the decoder's bilinear x2, the 1x1 output).
pub fn relighting(c: &RelightingConfig, batch: usize, side: usize) -> f64 {
    let b = batch as f64;
    let mut total = 0.0;
    let mut c_in = c.in_channels();
    let mut r = side;
    for (level, &ch) in c.channels.iter().enumerate() {
        if level > 0 {
            r /= 2;
        }
        total += b * (conv2d(c_in, ch, 3, r, r) + conv2d(ch, ch, 3, r, r));
        c_in = ch;
    }
    for level in (0..c.channels.len() - 1).rev() {
        let ch = c.channels[level];
        total += b * bilinear_upsample(c_in, r, r, 2);
        r *= 2;
        total += b * (conv2d(c_in + ch, ch, 3, r, r) + conv2d(ch, ch, 3, r, r));
        c_in = ch;
    }
    total + b * conv2d(c_in, 3, 1, r, r)
}

/// FLOPs of each part of one generator forward pass.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct GeneratorFlops {
    pub mapping: f64,
    /// The NeIIF at the composited samples (both passes).
    pub field: f64,
    /// The density-only proposal passes (forward only, no autodiff).
    pub proposal: f64,
    /// An estimate (elementwise work).
    pub compositing: f64,
    pub upsampler: f64,
    /// The shading maps' bilinear upsampling and the U-Net.
    pub relighting: f64,
}

impl GeneratorFlops {
    pub fn total(&self) -> f64 {
        self.differentiated() + self.proposal
    }

    /// The work the backward pass goes through again: all but the proposal passes.
    pub fn differentiated(&self) -> f64 {
        self.mapping + self.field + self.compositing + self.upsampler + self.relighting
    }
}

/// One forward pass of the generator on `batch` latents, computing what `wants` asks (as
/// [`crate::generator::Generator::forward`] decides it).
pub fn generator(c: &GeneratorConfig, batch: usize, wants: GeneratorWants) -> GeneratorFlops {
    let side = c.volume_resolution;
    let rays = side * side;
    let r = &c.renderer;
    let upsample = wants.needs_upsampler();
    let shading = wants.needs_shading();
    let field_wants = FieldWants {
        normals: wants.normals_lo || shading,
        appearance: wants.albedo_lo || wants.features_lo || upsample || shading,
    };
    let field_pass = |samples| field(&c.neiif, batch, rays * samples, field_wants);
    let mut channels = 0;
    if wants.albedo_lo || upsample {
        channels += 3;
    }
    if wants.normals_lo {
        channels += 3;
    }
    if wants.features_lo || upsample {
        channels += c.neiif.width;
    }
    if shading {
        channels += 6;
    }
    if wants.depth {
        channels += 1;
    }
    let lobes = if shading { c.neiif.specular_lobes } else { 0 };
    let blocks = (c.output_resolution / side).trailing_zeros() as usize;
    let feature_channels = c.upsampler_channels - 3;
    GeneratorFlops {
        mapping: mapping(&c.mapping, batch),
        field: field_pass(r.stratified)
            + if r.importance > 0 {
                field_pass(r.importance)
            } else {
                0.0
            },
        proposal: proposal(c, batch, rays),
        compositing: compositing(batch, rays, r.stratified, r.importance, channels, lobes),
        upsampler: if upsample {
            let u = UpsamplerConfig::new(
                c.mapping.w_dim,
                3 + c.neiif.width,
                c.upsampler_channels,
                blocks,
            )
            .with_kernel(c.upsampler_kernel);
            upsampler(&u, batch, side) + upsampler_noise(&u, c.upsampler_noise, batch, side)
        } else {
            0.0
        },
        relighting: if wants.relit {
            let f = c.output_resolution / side;
            2.0 * batch as f64 * bilinear_upsample(3, side, side, f)
                + relighting(
                    &RelightingConfig::new(feature_channels)
                        .with_channels(c.relighting_channels.clone()),
                    batch,
                    c.output_resolution,
                )
        } else {
            0.0
        },
    }
}

/// One forward pass of a discriminator on a batch: FromRGB, per block the 3x3 convolution,
/// the blur (4x4, padding 2) and strided 3x3 convolution, the skip's blur-downsample and 1x1
/// convolution; the epilogue's 3x3 convolution and two fully connected layers.
pub fn discriminator(c: &DiscriminatorConfig, batch: usize) -> f64 {
    let b = batch as f64;
    let mut r = c.resolution;
    let mut total = b * conv2d(c.in_channels, c.channels_at(r), 1, r, r);
    while r > 4 {
        let (cin, cout, h) = (c.channels_at(r), c.channels_at(r / 2), r / 2);
        total += b
            * (conv2d(cin, cin, 3, r, r)
                + depthwise(cin, 16, r + 1, r + 1)
                + conv2d(cin, cout, 3, h, h)
                + depthwise(cin, 16, h, h)
                + conv2d(cin, cout, 1, h, h));
        r = h;
    }
    let c4 = c.channels_at(4);
    total
        + b * conv2d(c4 + c.mbstd_channels, c4, 3, 4, 4)
        + matmul(batch, c4, 16 * c4)
        + matmul(batch, 1, c4)
}

/// A discriminator's logits and explicit input gradient (R1's forward): the reverse sweep
/// applies the adjoint of every convolution, blur and matmul of the forward pass, each
/// costing what the forward operation does, so twice the forward.
pub fn discriminator_input_gradient(c: &DiscriminatorConfig, batch: usize) -> f64 {
    2.0 * discriminator(c, batch)
}

/// An Adam step over `params` parameters: about 12 elementwise operations each (moments,
/// bias corrections, square root, division, update). An estimate.
pub fn adam(params: usize) -> f64 {
    12.0 * params as f64
}

/// A moving-average update over `params` parameters: `beta p + (1 - beta) q`. An estimate.
pub fn ema(params: usize) -> f64 {
    3.0 * params as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn primitive_formulas_match_hand_counts() {
        // [2, 3] x [3, 4]: 8 outputs of 3 multiply-adds.
        assert_eq!(matmul(2, 4, 3), 48.0);
        // 3x3 conv, 2 -> 5 channels, 4x4 output: 16 * 5 outputs of 18 multiply-adds.
        assert_eq!(conv2d(2, 5, 3, 4, 4), 2.0 * 16.0 * 5.0 * 18.0);
        assert_eq!(depthwise(3, 9, 2, 2), 2.0 * 3.0 * 9.0 * 4.0);
        // x2: a 4x4 tent over the padded 4x4 input of a 2x2 image, 1 channel.
        assert_eq!(bilinear_upsample(1, 2, 2, 2), 2.0 * 16.0 * 16.0);
        assert_eq!(bilinear_upsample(7, 2, 2, 1), 0.0);
    }

    #[test]
    fn mapping_counts_every_layer() {
        let c = MappingNetworkConfig::new()
            .with_z_dim(4)
            .with_w_dim(8)
            .with_layers(3);
        // Batch 2: 4 -> 8, then 8 -> 8 twice.
        assert_eq!(mapping(&c, 2), 2.0 * 2.0 * (32.0 + 64.0 + 64.0));
    }

    #[test]
    fn field_counts_the_reverse_sweep_through_the_density_layer() {
        let c = NeiifConfig::new()
            .with_w_dim(2)
            .with_width(4)
            .with_layers(3)
            .with_density_layer(2)
            .with_frequencies(1)
            .with_head_width(5)
            .with_specular_lobes(1);
        // Encoding: 3 + 6 = 9 channels. One element, 10 points.
        let m = |d_in: f64, d_out: f64| 2.0 * (d_in * 2.0 + d_out * d_in);
        let density_only = m(9.0, 4.0) + 2.0 * 10.0 * 4.0 * 9.0 // layer 1
            + m(4.0, 4.0) + 2.0 * 10.0 * 4.0 * 4.0 // layer 2
            + 2.0 * 10.0 * 4.0; // density head
        assert_eq!(field(&c, 1, 10, FieldWants::DENSITY), density_only);
        let with_normals = m(9.0, 4.0) + 2.0 * 2.0 * 10.0 * 36.0
            + m(4.0, 4.0) + 2.0 * 2.0 * 10.0 * 16.0
            + 2.0 * 10.0 * 4.0
            + m(4.0, 4.0) + 2.0 * 10.0 * 16.0 // layer 3
            + 2.0 * 10.0 * 5.0 * 4.0 + 2.0 * 10.0 * 4.0 * 5.0; // head
        assert_eq!(field(&c, 1, 10, FieldWants::ALL), with_normals);
        // Template planes of 2 channels: layer 1 takes 11 inputs, and the gathers cost 2 x
        // 27 taps x 2 channels per output (1, or 4 with normals), the fold 6 x 2 per point.
        let t = c
            .clone()
            .with_template_resolution(8)
            .with_template_channels(2);
        let density_only = m(11.0, 4.0)
            + 2.0 * 10.0 * 4.0 * 11.0
            + m(4.0, 4.0)
            + 2.0 * 10.0 * 4.0 * 4.0
            + 2.0 * 10.0 * 4.0
            + 10.0 * 2.0 * 54.0;
        assert_eq!(field(&t, 1, 10, FieldWants::DENSITY), density_only);
        let extra = (m(11.0, 4.0) - m(9.0, 4.0))
            + 2.0 * 2.0 * 10.0 * 4.0 * 2.0
            + 10.0 * 2.0 * (54.0 * 4.0 + 6.0);
        assert_eq!(field(&t, 1, 10, FieldWants::ALL), with_normals + extra);
        // A basis of 3 sets: the coefficients (3 x 2 multiply-adds of w per latent) and 3
        // multiply-adds per entry of the 192 x 2 planes, for each of 2 latents.
        let b = t.clone().with_template_basis(3);
        let basis = 2.0 * (2.0 * 3.0 * 2.0) + 2.0 * (2.0 * 3.0 * 192.0 * 2.0);
        assert_eq!(
            field(&b, 2, 10, FieldWants::DENSITY),
            field(&t, 2, 10, FieldWants::DENSITY) + basis
        );
    }

    #[test]
    fn discriminator_at_8x8_has_one_block_and_the_epilogue() {
        let c = DiscriminatorConfig::new(3, 8)
            .with_channel_base(64)
            .with_channel_max(16);
        // channels: 8 at 8x8, 16 at 4x4.
        let want = conv2d(3, 8, 1, 8, 8)
            + conv2d(8, 8, 3, 8, 8)
            + depthwise(8, 16, 9, 9)
            + conv2d(8, 16, 3, 4, 4)
            + depthwise(8, 16, 4, 4)
            + conv2d(8, 16, 1, 4, 4)
            + conv2d(17, 16, 3, 4, 4)
            + matmul(1, 16, 256)
            + matmul(1, 1, 16);
        assert_eq!(discriminator(&c, 1), want);
        assert_eq!(discriminator(&c, 3), 3.0 * want);
        assert_eq!(discriminator_input_gradient(&c, 1), 2.0 * want);
    }

    #[test]
    fn upsampler_counts_both_layers_of_each_block_at_either_kernel() {
        // w of 2, 5 input channels, 4 channels, one block on a 3x3 input of one element.
        let m = |d_in: f64, d_out: f64| 2.0 * (d_in * 2.0 + d_out * d_in);
        let c = UpsamplerConfig::new(2, 5, 4, 1);
        let rest = bilinear_upsample(3, 3, 3, 2) + depthwise(4, 9, 6, 6);
        let one = m(5.0, 4.0) + 2.0 * 9.0 * 4.0 * 5.0 + m(4.0, 16.0) + 2.0 * 9.0 * 16.0 * 4.0;
        assert_eq!(upsampler(&c, 1, 3), one + rest);
        // 3x3: each layer reads 9 taps of every input channel.
        let three = m(45.0, 4.0) + 2.0 * 9.0 * 4.0 * 45.0 + m(36.0, 16.0) + 2.0 * 9.0 * 16.0 * 36.0;
        assert_eq!(upsampler(&c.clone().with_kernel(3), 1, 3), three + rest);
    }

    #[test]
    fn upsampler_noise_counts_each_blocks_gain_layer_at_its_output() {
        // w of 2, 4 channels, 2 octaves, two blocks on a 3x3 input of one element: gains of 8
        // channels at 6x6 and at 12x12.
        let c = UpsamplerConfig::new(2, 5, 4, 2);
        let m = 2.0 * (4.0 * 2.0 + 8.0 * 4.0);
        let block = |pixels: f64| m + 2.0 * pixels * 8.0 * 4.0 + 3.0 * pixels * 8.0;
        assert_eq!(upsampler_noise(&c, 2, 1, 3), block(36.0) + block(144.0));
        assert_eq!(upsampler_noise(&c, 0, 1, 3), 0.0);
    }

    #[test]
    fn relighting_counts_both_levels() {
        let c = RelightingConfig::new(1).with_channels(vec![2, 4]);
        // 10 input channels at 8x8; level 2 at 4x4; decoder back at 8x8 on 4 + 2 channels.
        let want = conv2d(10, 2, 3, 8, 8)
            + conv2d(2, 2, 3, 8, 8)
            + conv2d(2, 4, 3, 4, 4)
            + conv2d(4, 4, 3, 4, 4)
            + bilinear_upsample(4, 4, 4, 2)
            + conv2d(6, 2, 3, 8, 8)
            + conv2d(2, 2, 3, 8, 8)
            + conv2d(2, 3, 1, 8, 8);
        assert_eq!(relighting(&c, 1, 8), want);
    }

    #[test]
    fn stage_one_generator_runs_no_relighting_and_shades_nothing() {
        let c = GeneratorConfig::small();
        let one = generator(&c, 2, GeneratorWants::STAGE1);
        let all = generator(&c, 2, GeneratorWants::ALL);
        assert_eq!(one.relighting, 0.0);
        assert!(one.mapping > 0.0 && one.field > 0.0 && one.upsampler > 0.0);
        assert!(all.compositing > one.compositing);
        assert_eq!(
            all.field, one.field,
            "stage 1 already needs normals and appearance"
        );
        assert!(all.relighting > 0.0);
        assert_eq!(
            generator(&c, 4, GeneratorWants::STAGE1).mapping,
            2.0 * one.mapping
        );
    }
}
