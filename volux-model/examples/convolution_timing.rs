//! Times the small discriminator's convolutions and blurs one layer shape at a time on the CPU
//! backend: each convolution forward, its adjoint and forward + backward (input and weight
//! gradients), with the rate each reaches; then each blur's forward and adjoint.
//!
//! `cargo run -p volux-model --example convolution_timing [--release] -- [batch] [repeats]`
//! (defaults 8, the discriminator step's reals and fakes, and 9 repeats). Like
//! `neiif_timing`, this process keeps glibc's default allocator settings, unlike the `volux`
//! binary; run it with `MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_=2147483647` to match them.

use burn::tensor::{Device, Distribution, Tensor};
use volux_model::backend::to_f32_vec;
use volux_model::convolution::{ConvGeometry, conv2d, conv2d_adjoint};
use volux_model::fir_filter::{Fir, fir2d, fir2d_adjoint};
#[path = "common/timing.rs"]
mod timing;
use timing::median_ms;

/// `(channels in, channels out, kernel, input side, stride, padding)` of the small
/// discriminator at 64x64: the input layer, each block's two convolutions and its skip.
const LAYERS: [(usize, usize, usize, usize, usize, usize); 9] = [
    (3, 32, 1, 64, 1, 0),
    (32, 32, 3, 64, 1, 1),
    (32, 64, 3, 65, 2, 0),
    (32, 64, 1, 64, 2, 0),
    (64, 64, 3, 32, 1, 1),
    (64, 128, 3, 33, 2, 0),
    (128, 128, 3, 16, 1, 1),
    (128, 128, 3, 17, 2, 0),
    (128, 128, 3, 8, 1, 1),
];

/// Reads one element, so that a timed closure waits for its result.
fn touch(t: Tensor<4>) {
    to_f32_vec(t.slice([0..1, 0..1, 0..1, 0..1]));
}

fn main() {
    let args: Vec<usize> = std::env::args()
        .skip(1)
        .map(|a| a.parse().expect("arguments are integers"))
        .collect();
    let batch = args.first().copied().unwrap_or(8);
    let repeats = args.get(1).copied().unwrap_or(9);
    let plain = Device::flex();
    let autodiff = plain.clone().autodiff();
    println!("small discriminator's layers, batch {batch}, median of {repeats}");
    let mut total = [0.0f64; 3];
    for (c, o, k, side, stride, pad) in LAYERS {
        let g = ConvGeometry::new(stride, pad);
        let out = g.out_len(side, k);
        let normal = Distribution::Normal(0.0, 1.0);
        let x = Tensor::<4>::random([batch, c, side, side], normal, &plain);
        let w = Tensor::<4>::random([o, c, k, k], normal, &plain);
        let y = Tensor::<4>::random([batch, o, out, out], normal, &plain);
        let forward = median_ms(repeats, || touch(conv2d(x.clone(), w.clone(), g)));
        let adjoint = median_ms(repeats, || {
            touch(conv2d_adjoint(y.clone(), w.clone(), g, [side, side]))
        });
        let xa = Tensor::<4>::from_data(x.to_data(), &autodiff).require_grad();
        let wa = Tensor::<4>::from_data(w.to_data(), &autodiff).require_grad();
        let both = median_ms(repeats, || {
            let grads = conv2d(xa.clone(), wa.clone(), g).sum().backward();
            to_f32_vec(wa.grad(&grads).expect("tracked"));
        });
        let flops = 2.0 * (batch * o * c * k * k * out * out) as f64;
        let rate = |ms: f64, times: f64| times * flops / ms / 1e6;
        println!(
            "conv {c:3} -> {o:3}, {k}x{k}, {side:2}^2, stride {stride}: forward {forward:6.2} ms \
             ({:5.1} GFLOP/s), adjoint {adjoint:6.2} ms ({:5.1}), forward + backward \
             {both:6.2} ms ({:5.1})",
            rate(forward, 1.0),
            rate(adjoint, 1.0),
            rate(both, 3.0)
        );
        total[0] += forward;
        total[1] += adjoint;
        total[2] += both;
    }
    println!(
        "convolutions: forward {:.1} ms, adjoint {:.1} ms, forward + backward {:.1} ms",
        total[0], total[1], total[2]
    );
    let mut blurs = 0.0;
    for (c, side) in [(32, 64), (64, 32), (128, 16)] {
        for (pad, stride) in [(2, 1), (1, 2)] {
            let fir = Fir::new(vec![0.125, 0.375, 0.375, 0.125], pad, stride);
            let x = Tensor::<4>::random(
                [batch, c, side, side],
                Distribution::Normal(0.0, 1.0),
                &plain,
            );
            let y = fir2d(x.clone(), &fir);
            let forward = median_ms(repeats, || touch(fir2d(x.clone(), &fir)));
            let adjoint = median_ms(repeats, || {
                touch(fir2d_adjoint(y.clone(), &fir, [side, side]))
            });
            println!(
                "blur {c:3} channels, {side:2}^2, padding {pad}, stride {stride}: forward \
                 {forward:5.2} ms, adjoint {adjoint:5.2} ms"
            );
            blurs += forward + adjoint;
        }
    }
    println!("blurs: forward + adjoint {blurs:.1} ms");
}
