//! Times the NeIIF on the CPU backend at the quickstart's size: forward without autodiff,
//! forward recorded by autodiff, and forward + backward, each with every output (density,
//! normals by the reverse sweep, albedo, specular weights, features) as the renderer asks for them.
//!
//! `cargo run -p volux-model --example neiif_timing [--release] -- [points] [batch] [repeats]`
//! (defaults 8192 points per batch element, i.e. one of the renderer's two passes at 8 + 8
//! samples on 32x32 rays, batch 4, 5 repeats); the `small` preset's field with the
//! quickstart's 4 octaves and sphere prior. This process keeps glibc's default allocator,
//! unlike the `volux` binary (`src/allocator.rs`): page faults on fresh allocations were a fifth
//! of a profile of it, so compare its figures with each other, not with `volux train bench`.

use burn::tensor::{Device, Distribution, Tensor};
use volux_model::backend::to_f32_vec;
use volux_model::field::FieldWants;
use volux_model::neiif::NeiifConfig;
#[path = "common/timing.rs"]
mod timing;
use timing::median_ms;

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("arguments are integers"))
        .collect();
    let points = args.first().copied().unwrap_or(8192);
    let batch = args.get(1).copied().unwrap_or(4);
    let repeats = args.get(2).copied().unwrap_or(5);

    let config = NeiifConfig::new()
        .with_w_dim(128)
        .with_width(64)
        .with_head_width(64)
        .with_frequencies(4)
        .with_sphere_prior(10.0)
        .with_sphere_radius(0.35);
    let plain = Device::flex();
    let autodiff = plain.clone().autodiff();
    let field_plain = config.init(&plain);
    let field = config.init(&autodiff);
    let x_shape = [batch, points, 3];
    let make = |device: &Device| {
        (
            Tensor::<3>::random(x_shape, Distribution::Uniform(-0.5, 0.5), device),
            Tensor::<2>::random([batch, 128], Distribution::Normal(0.0, 1.0), device),
        )
    };
    let (x_plain, w_plain) = make(&plain);
    let (x, w) = make(&autodiff);
    println!("small NeIIF, batch {batch}, {points} points each, every output, median of {repeats}");

    let forward = median_ms(repeats, || {
        let out = field_plain.forward(x_plain.clone(), w_plain.clone(), FieldWants::ALL);
        to_f32_vec(out.features.expect("asked"));
    });
    let recorded = median_ms(repeats, || {
        let out = field.forward(x.clone(), w.clone(), FieldWants::ALL);
        to_f32_vec(out.features.expect("asked"));
    });
    let backward = median_ms(repeats, || {
        let out = field.forward(x.clone(), w.clone(), FieldWants::ALL);
        let loss = out.sigma.sum()
            + out.normals.expect("asked").sum()
            + out.albedo.expect("asked").sum()
            + out.specular_weights.expect("asked").sum()
            + out.features.expect("asked").sum();
        let _ = loss.backward();
    });
    println!("forward (no autodiff): {forward:.1} ms");
    println!("forward (autodiff):    {recorded:.1} ms");
    println!("forward + backward:    {backward:.1} ms");
}
