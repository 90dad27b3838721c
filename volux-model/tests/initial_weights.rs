//! The generator's networks draw their initial weights in a fixed order.
//!
//! A test of its own binary, so of its own process: the backend's random generator is one
//! for the whole process, and a test drawing from it beside this one (the library's tests run
//! on as many threads as the machine has cores) would move the draws between the two inits
//! compared here. This file must hold no other test.

use burn::tensor::{Device, Tensor};
use volux_model::backend::to_f32_vec;
use volux_model::generator::GeneratorConfig;
use volux_model::relighting::RelightingConfig;
use volux_model::upsampler::UpsamplerConfig;

#[test]
fn the_networks_draw_their_initial_weights_in_a_fixed_order() {
    // A training run is a pure function of its seed, and the documented A/Bs compare runs
    // bit for bit: reordering the draws changes every initial weight. The order is NeIIF,
    // upsampler, relighting network, mapping network, then the options (the upsampler's noise).
    let device = Device::flex();
    let config = GeneratorConfig::small();
    device.seed(5);
    let g = config.init(&device).unwrap();
    device.seed(5);
    let neiif = config.neiif.init(&device);
    let upsampler = UpsamplerConfig::new(
        config.mapping.w_dim,
        3 + neiif.feature_dim(),
        config.upsampler_channels,
        1,
    )
    .init(&device);
    let relighting = RelightingConfig::new(config.upsampler_channels - 3)
        .with_channels(config.relighting_channels.clone())
        .init(&device);
    let mapping = config.mapping.init(&device);
    let same = |a: Vec<f32>, b: Vec<f32>, what: &str| {
        assert!(a == b, "the {what}'s initial weights moved");
    };
    let weights = |t: Tensor<2>| to_f32_vec(t);
    same(
        weights(g.neiif.layers[0].weight.val()),
        weights(neiif.layers[0].weight.val()),
        "NeIIF",
    );
    same(
        weights(g.upsampler.blocks[0].conv1.weight.val()),
        weights(upsampler.blocks[0].conv1.weight.val()),
        "upsampler",
    );
    same(
        to_f32_vec(g.relighting.out.weight.val()),
        to_f32_vec(relighting.out.weight.val()),
        "relighting network",
    );
    same(
        weights(g.mapping.layers[0].weight.val()),
        weights(mapping.layers[0].weight.val()),
        "mapping",
    );
    // The upsampler's noise inputs draw after all four: turning them on moves no other
    // initial weight.
    device.seed(5);
    let noised = config
        .clone()
        .with_upsampler_noise(2)
        .init(&device)
        .unwrap();
    assert_eq!(noised.upsampler.noise_octaves(), 2);
    same(
        weights(noised.neiif.layers[0].weight.val()),
        weights(g.neiif.layers[0].weight.val()),
        "NeIIF (with noise)",
    );
    same(
        weights(noised.upsampler.blocks[0].conv2.weight.val()),
        weights(g.upsampler.blocks[0].conv2.weight.val()),
        "upsampler (with noise)",
    );
    same(
        to_f32_vec(noised.relighting.out.weight.val()),
        to_f32_vec(g.relighting.out.weight.val()),
        "relighting network (with noise)",
    );
    same(
        weights(noised.mapping.layers[7].weight.val()),
        weights(g.mapping.layers[7].weight.val()),
        "mapping (with noise)",
    );
}
