//! Times the discriminator on the CPU backend: forward, the explicit input gradient, and the
//! R1 penalty with its backward pass (the lazy-regularisation step), next to a plain forward +
//! backward (the main D step).
//!
//! `cargo run -p volux-model --example discriminator_timing [--release] -- [resolution]
//! [batch] [repeats]` (defaults 64, 8, 5); the small preset with 3 input channels.

use burn::tensor::{Device, Distribution, Tensor};
use volux_model::backend::to_f32_vec;
use volux_model::discriminator::{DiscriminatorConfig, r1_penalty};
#[path = "common/timing.rs"]
mod timing;
use timing::median_ms;

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("arguments are integers"))
        .collect();
    let resolution = args.first().copied().unwrap_or(64);
    let batch = args.get(1).copied().unwrap_or(8);
    let repeats = args.get(2).copied().unwrap_or(5);

    let config = DiscriminatorConfig::small(3, resolution);
    let plain = Device::flex();
    let autodiff = plain.clone().autodiff();
    let d_plain = config.init(&plain);
    let d = config.init(&autodiff);
    let shape = [batch, 3, resolution, resolution];
    let x_plain = Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &plain);
    let x = Tensor::<4>::random(shape, Distribution::Normal(0.0, 1.0), &autodiff);
    println!(
        "small preset, {resolution}x{resolution}, batch {batch}, {} parameters, median of {repeats}",
        d.num_params()
    );

    let forward = median_ms(repeats, || {
        to_f32_vec(d_plain.forward(x_plain.clone()));
    });
    let input_gradient = median_ms(repeats, || {
        let (_, g) = d_plain.input_gradient(x_plain.clone());
        to_f32_vec(g);
    });
    let main_step = median_ms(repeats, || {
        let _ = d.forward(x.clone()).sum().backward();
    });
    let r1_step = median_ms(repeats, || {
        let (_, penalty) = r1_penalty(&d, x.clone(), 1.0);
        let _ = penalty.backward();
    });
    println!("forward (no autodiff)                {forward:8.1} ms");
    println!("forward + input gradient (no autodiff) {input_gradient:6.1} ms");
    println!("forward + backward (main D step)     {main_step:8.1} ms");
    println!("R1 penalty + backward (D reg step)   {r1_step:8.1} ms");
}
