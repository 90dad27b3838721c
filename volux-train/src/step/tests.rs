use std::path::Path;

use burn::tensor::{Device, Distribution};
use volux_model::backend::to_f32_vec;

use super::*;
use crate::config::TrainConfig;
use crate::losses::area_downsample;
use crate::progressive::faded_input;
use volux_data::layers::Layers;

/// One pass per discriminator serves both phases: the generator's gradient through the
/// pullback equals backpropagation of its loss through the frozen discriminator, and the
/// discriminator's weight gradient from the kept logits equals a second pass's on the
/// detached fakes (what the step computed before).
#[test]
fn one_verdict_gives_both_phases_the_gradients_of_separate_passes() {
    use burn::module::Param;
    use volux_model::discriminator::DiscriminatorConfig;

    let device = Device::flex().autodiff();
    device.seed(7);
    let disc = |seed| {
        device.seed(seed);
        DiscriminatorConfig::new(3, 16)
            .with_channel_base(128)
            .with_channel_max(32)
            .init(&device)
    };
    let (d_a, d_g) = (disc(8), disc(9));
    // A stand-in generator: fakes are a tracked function of one parameter.
    let theta = Param::from_tensor(Tensor::<4>::random(
        [4, 3, 16, 16],
        Distribution::Normal(0.0, 1.0),
        &device,
    ));
    let fakes = |t: &Tensor<4>| (t.clone().mul_scalar(1.5).tanh(), t.clone().sin());
    let (fa, fg) = fakes(&theta.val());
    let judged: Vec<Pair> = vec![
        (
            DiscriminatorRole::AlbedoLow.terms(),
            DiscriminatorRole::AlbedoLow,
            &d_a,
            fa,
            None,
            1.0,
        ),
        (
            DiscriminatorRole::Geometry.terms(),
            DiscriminatorRole::Geometry,
            &d_g,
            fg,
            None,
            0.3,
        ),
    ];
    let mut outcome = StepOutcome::default();
    let verdicts = judge(&judged, true, &mut outcome);
    let in_turn = judge(&judged, false, &mut StepOutcome::default());
    let bits = |t: Tensor<2>| {
        to_f32_vec(t)
            .iter()
            .map(|v| v.to_bits())
            .collect::<Vec<_>>()
    };
    for (a, b) in verdicts.fake_logits.iter().zip(&in_turn.fake_logits) {
        assert_eq!(
            bits(a.clone()),
            bits(b.clone()),
            "side by side is in turn, bit for bit"
        );
    }
    let root = verdicts.root.clone().unwrap();
    let turn_root = in_turn.root.unwrap();
    assert_eq!(scalar(&root).to_bits(), scalar(&turn_root).to_bits());
    let g_new = theta.val().grad(&root.backward()).unwrap();

    // Before: the generator's loss through frozen discriminators, then a second forward.
    let (fa, fg) = fakes(&theta.val());
    let (frozen_a, frozen_g) = (Module::no_grad(d_a.clone()), Module::no_grad(d_g.clone()));
    let la = generator_loss(frozen_a.forward(fa.clone()));
    let lg = generator_loss(frozen_g.forward(fg.clone()));
    let value = scalar(&la) + 0.3 * scalar(&lg);
    let g_old = theta
        .val()
        .grad(&(la + lg.mul_scalar(0.3)).backward())
        .unwrap();
    assert!(
        (verdicts.value - value).abs() <= 1e-6 * value.abs(),
        "{} vs {value}",
        verdicts.value
    );
    assert_eq!(outcome.losses.len(), 2);
    let close = |got: Vec<f32>, want: Vec<f32>, what: &str| {
        let scale = want.iter().fold(0f32, |m, v| m.max(v.abs()));
        let err = got
            .iter()
            .zip(&want)
            .fold(0f32, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            scale > 0.0 && err <= 1e-5 * scale,
            "{what}: error {err:e}, largest {scale:e}"
        );
    };
    close(to_f32_vec(g_new), to_f32_vec(g_old), "generator gradient");

    // The discriminator phase (`judge_reals`, with and without R1, side by side and in
    // turn) against a second pass on the detached fakes.
    let real = Tensor::<4>::random([4, 3, 16, 16], Distribution::Normal(0.0, 1.0), &device);
    let with_reals: Vec<Pair> = judged
        .iter()
        .map(|(n, r, d, f, _, w)| (*n, *r, *d, f.clone(), Some(real.clone()), *w))
        .collect();
    for r1 in [None, Some((0.5, 4))] {
        let run = |cpu| {
            // Fresh logits each time: a backward pass consumes its graph.
            let logits = judge(&judged, true, &mut StepOutcome::default()).fake_logits;
            let items: Vec<(&Pair, Tensor<2>)> = with_reals.iter().zip(logits).collect();
            side_by_side(&items, cpu, |(pair, logits)| {
                judge_reals(pair, logits.clone(), r1)
            })
        };
        let (side, turn) = (run(true), run(false));
        for (i, ((_, _, d, fake, _, weight), (mut a, mut b))) in with_reals
            .iter()
            .zip(side.into_iter().zip(turn))
            .enumerate()
        {
            let w = d.blocks[0].conv0.weight.val();
            let id = d.blocks[0].conv0.weight.id;
            let (ga, gb) = (
                a.grads.as_mut().unwrap().remove::<4>(id).unwrap(),
                b.grads.as_mut().unwrap().remove::<4>(id).unwrap(),
            );
            let (ga, gb) = (to_f32_vec(ga), to_f32_vec(gb));
            assert_eq!(
                ga.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                gb.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "side by side is in turn, bit for bit"
            );
            assert_eq!(a.term.to_bits(), b.term.to_bits());
            assert_eq!(a.r1.is_some(), r1.is_some());
            let mut again =
                discriminator_loss(d.forward(real.clone()), d.forward(fake.clone().detach()));
            if let Some((gamma, interval)) = r1 {
                again = discriminator_loss(
                    lazy_r1(d, real.clone(), gamma, interval).0,
                    d.forward(fake.clone().detach()),
                ) + lazy_r1(d, real.clone(), gamma, interval).1;
            }
            let again = again.mul_scalar(*weight);
            assert!(
                (a.term - scalar(&again)).abs() <= 1e-6 * (1.0 + a.term.abs()),
                "{i}"
            );
            close(
                ga,
                to_f32_vec(w.grad(&again.backward()).unwrap()),
                "discriminator gradient",
            );
        }
    }
}

/// Small discriminators run side by side on the CPU, the paper's in turn.
#[test]
fn small_discriminators_run_side_by_side_and_large_ones_in_turn() {
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    let device = Device::flex().autodiff();
    let quickstart = TrainConfig::load(&configs.join("quickstart.toml")).unwrap();
    assert!(side_by_side_on(&device, &quickstart));
    assert!(side_by_side_on(&Device::flex(), &quickstart));
    let celeba = TrainConfig::load(&configs.join("celeba128.toml")).unwrap();
    assert!(!side_by_side_on(&device, &celeba));
}

/// The discriminators see what the step hands them: the reals' shading brought to the
/// fakes' resolution, and the high-resolution albedo (real and fake) faded while the
/// upsampler fades in, then as it is once grown.
#[test]
fn each_discriminator_gets_reals_and_fakes_through_the_same_door() {
    let device = Device::flex();
    device.seed(4);
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quickstart.toml");
    let config = TrainConfig::load(&path).unwrap();
    let d = Discriminators::init(&config, &device);
    let random =
        |c, side| Tensor::<4>::random([4, c, side, side], Distribution::Uniform(0.0, 1.0), &device);
    let reals = Layers {
        photo: random(3, 64),
        relit: random(3, 64),
        albedo_hi: random(3, 64),
        albedo_lo: random(3, 32),
        normals_lo: random(3, 32),
        mask: random(1, 64),
        diffuse: random(3, 64),
        specular: random(3, 64),
    };
    let tensors: BatchTensors = reals.map(|_, t| Some(t.clone()));
    let fake_hi = random(3, 64);
    let fakes = Fakes {
        albedo_lo: Some(random(3, 32)),
        albedo_hi: Some(fake_hi.clone()),
        geometry: Some(random(3, 32)),
        shading: Some(random(9, 64)),
        photo: Some(random(3, 64)),
    };
    let same = |a: &Tensor<4>, b: Tensor<4>| to_f32_vec(a.clone()) == to_f32_vec(b);
    let find = |pairs: &[Pair], role| {
        let p = pairs.iter().find(|p| p.1 == role).expect("active");
        (p.3.clone(), p.4.clone().expect("reals given"))
    };
    let w = config.loss;

    let fading = pairs(&d, &fakes, Some(&tensors), &w, Some(&[0.0]));
    assert_eq!(fading.len(), 5);
    let (fake, real) = find(&fading, DiscriminatorRole::AlbedoHigh);
    assert!(same(
        &real,
        faded_input(reals.albedo_hi.clone(), Some(&[0.0]))
    ));
    assert!(!same(&real, reals.albedo_hi.clone()));
    assert!(same(&fake, faded_input(fake_hi.clone(), Some(&[0.0]))));
    let (_, real) = find(&fading, DiscriminatorRole::Shading);
    let want = shading_condition_lo(
        reals.relit.clone(),
        area_downsample(reals.diffuse.clone(), 2),
        area_downsample(reals.specular.clone(), 2),
    );
    assert!(same(&real, want));

    let grown = pairs(&d, &fakes, Some(&tensors), &w, None);
    let (fake, real) = find(&grown, DiscriminatorRole::AlbedoHigh);
    assert!(same(&real, reals.albedo_hi.clone()) && same(&fake, fake_hi));
}

/// The density regulariser joins the generator's terms only when asked; on a fresh field
/// (the sphere prior's soft ball) it is finite and positive, and its gradient reaches the
/// field's first layer, the template planes and, through `w`, the mapping network.
#[test]
fn the_density_regulariser_is_a_term_of_the_generator_only_when_asked() {
    let device = Device::flex().autodiff();
    device.seed(3);
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs/quickstart.toml");
    let config = TrainConfig::load(&path).unwrap();
    let gc = config.generator();
    let g = gc.init(&device).unwrap();
    let reals: BatchTensors = Layers::from_fn(|_| None);
    let poses = [Pose::default()];
    let z = Tensor::<2>::random(
        [1, gc.mapping.z_dim],
        Distribution::Normal(0.0, 1.0),
        &device,
    );
    let run = |density: bool| {
        let inputs = StepInputs {
            z: z.clone(),
            poses: &poses,
            lighting: None,
            reals: &reals,
            background: [1.0; 3],
            active: ActiveTerms {
                path: true,
                density,
                ..ActiveTerms::default()
            },
            weights: LossWeights {
                density_reg: 0.25,
                ..config.loss
            },
            fade: None,
            fade_discriminator: false,
            r1: None,
            lr_g: 0.0,
            lr_d: 0.0,
            side_by_side: false,
            poison: None,
        };
        generate(&g, &inputs).unwrap().1
    };
    let names = |r: &Regularisers| r.iter().map(|(n, w, _)| (*n, *w)).collect::<Vec<_>>();
    assert_eq!(names(&run(false)), [("path", 0.5)]);
    let with = run(true);
    assert_eq!(names(&with), [("path", 0.5), ("density_reg", 0.25)]);
    let term = with[1].2.clone();
    let value = scalar(&term);
    assert!(value.is_finite() && value > 0.0, "{value}");
    let grads = term.backward();
    let nonzero = |g: Option<Vec<f32>>, what: &str| {
        let g = g.unwrap_or_else(|| panic!("{what}: no gradient"));
        assert!(g.iter().all(|v| v.is_finite()), "{what}");
        assert!(g.iter().any(|&v| v != 0.0), "{what}: all zero");
    };
    nonzero(
        g.neiif.layers[0].weight.val().grad(&grads).map(to_f32_vec),
        "first layer",
    );
    let planes = g
        .neiif
        .template
        .as_ref()
        .expect("the quickstart has planes");
    nonzero(planes.planes.val().grad(&grads).map(to_f32_vec), "planes");
    nonzero(
        g.mapping.layers[0]
            .weight
            .val()
            .grad(&grads)
            .map(to_f32_vec),
        "mapping",
    );
}
