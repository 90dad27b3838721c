use super::*;

const TINY: &str = r#"
[model]
preset = "small"

[train]
batch = 4

[data]
resolution = 64
volume_resolution = 32
"#;

/// [`TINY`] with `keys` (TOML lines) added to its `[model]` table.
fn with_model(keys: &str) -> String {
    TINY.replace("\"small\"", &format!("\"small\"\n{keys}"))
}

fn load(text: &str) -> Result<TrainConfig, String> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.toml");
    std::fs::write(&path, text).unwrap();
    // The whole chain, as the binary prints it: `[data]` errors keep their causes.
    TrainConfig::load(&path).map_err(|e| volux_envmap::error::chain(&e))
}

/// A fresh field of `config`'s generator.
fn field_of(config: &TrainConfig) -> volux_model::neiif::Neiif {
    config.generator().neiif.init(&burn::tensor::Device::flex())
}

#[test]
fn a_small_config_loads_with_the_paper_defaults() {
    let c = load(TINY).unwrap();
    assert_eq!(c.train.batch, 4);
    assert_eq!((c.train.lr_g, c.train.lr_d), (0.0022, 0.0025));
    assert_eq!((c.train.beta1, c.train.beta2), (0.0, 0.99));
    assert_eq!(c.loss, LossWeights::default());
    assert_eq!(c.blocks(), 1);
    assert_eq!(c.generator().neiif.frequencies, 10);
}

#[test]
fn model_overrides_reach_the_generator() {
    let text = with_model(
        "stratified = 6\nimportance = 3\nsphere_prior = 10.0\nsphere_radius = 0.35\nfrequencies = 4",
    );
    let g = load(&text).unwrap().generator();
    assert_eq!((g.renderer.stratified, g.renderer.importance), (6, 3));
    assert_eq!((g.neiif.sphere_prior, g.neiif.sphere_radius), (10.0, 0.35));
    assert_eq!(g.neiif.frequencies, 4);
    assert_eq!(
        (g.renderer.proposal, g.renderer.refine),
        (0, 0),
        "EG3D's unless asked"
    );
    let text = with_model("stratified = 0\nproposal = 32\nrefine = 16\nimportance = 12");
    let c = load(&text).unwrap();
    let r = c.generator().renderer;
    assert_eq!(
        (r.stratified, r.proposal, r.refine, r.importance),
        (0, 32, 16, 12)
    );
    assert!(
        c.shapes().contains("proposal = 32"),
        "a resume must match it"
    );
    assert_eq!(g.renderer.shading, Shading::Volume, "volume unless asked");
    for (key, want) in [("volume", Shading::Volume), ("surface", Shading::Surface)] {
        let text = with_model(&format!("shading = \"{key}\""));
        let c = load(&text).unwrap();
        assert_eq!(c.generator().renderer.shading, want);
        // The shading mode is part of what a resumed run must match; writing out the
        // default changes nothing.
        let shapes = c.shapes();
        assert_eq!(
            shapes.contains("shading = \"surface\""),
            key == "surface",
            "{shapes}"
        );
        assert_eq!(shapes == load(TINY).unwrap().shapes(), key == "volume");
    }
}

#[test]
fn mapping_depth_and_discriminator_width_reach_the_networks() {
    let c = load(TINY).unwrap();
    assert_eq!(c.generator().mapping.layers, 8, "StyleGAN2's unless asked");
    let d = c.model.discriminator(DiscriminatorRole::Photo).unwrap();
    assert_eq!((d.channel_base, d.channel_max), (2048, 128), "the preset's");
    let text = with_model("mapping_layers = 2\nd_channel_base = 4096\nd_channel_max = 256");
    let c = load(&text).unwrap();
    assert_eq!(c.generator().mapping.layers, 2);
    for role in DiscriminatorRole::ALL {
        let d = c.model.discriminator(role).unwrap();
        assert_eq!((d.channel_base, d.channel_max), (4096, 256), "{role:?}");
        // 4096 / 64 = 64 channels at 64x64, 256 from 16x16 down.
        assert_eq!(d.channels_at(64), 64);
        assert_eq!(d.channels_at(16), 256);
    }
    // The volume's side moves the discriminators that judge volume-resolution images.
    let text = TINY
        .replace("\"small\"", "\"small\"\nvolume_resolution = 64")
        .replace("volume_resolution = 32", "volume_resolution = 64");
    let c64 = load(&text).unwrap();
    assert_eq!(c64.generator().volume_resolution, 64);
    assert_eq!(c64.blocks(), 0, "no upsampling");
    for (role, side) in [
        (DiscriminatorRole::AlbedoLow, 64),
        (DiscriminatorRole::Geometry, 64),
        (DiscriminatorRole::Photo, 64),
    ] {
        assert_eq!(c64.model.discriminator(role).unwrap().resolution, side);
    }
    // The template planes: none unless asked; they reach the field's first layer and are
    // part of what a resume must match.
    assert_eq!(load(TINY).unwrap().generator().neiif.template_resolution, 0);
    let text = with_model("template_resolution = 16\ntemplate_channels = 4");
    let planes = load(&text).unwrap();
    let g = planes.generator();
    assert_eq!(
        (g.neiif.template_resolution, g.neiif.template_channels),
        (16, 4)
    );
    let field = g.neiif.init(&burn::tensor::Device::flex());
    assert_eq!(
        field.template.as_ref().unwrap().planes.val().dims(),
        [3 * 16 * 16, 4]
    );
    assert!(planes.shapes().contains("template_resolution = 16"));
    assert_eq!(
        g.neiif.template_bound, 1.0,
        "planes over [-1, 1] unless asked"
    );
    let text = with_model("template_resolution = 16\ntemplate_bound = 0.6");
    let narrow = load(&text).unwrap();
    assert_eq!(narrow.generator().neiif.template_bound, 0.6);
    let field = narrow.generator().neiif.init(&burn::tensor::Device::flex());
    assert_eq!(field.template.as_ref().unwrap().bound, 0.6);
    assert_ne!(
        narrow.shapes(),
        planes.shapes(),
        "a resume must match the bound"
    );
    // A basis of planes: none unless asked; its sets and coefficients reach the field, and a
    // resume must match it.
    assert_eq!(planes.generator().neiif.template_basis, 0);
    assert!(field_of(&planes).template.unwrap().basis.is_none());
    let text = with_model("template_resolution = 16\ntemplate_channels = 4\ntemplate_basis = 5");
    let based = load(&text).unwrap();
    assert_eq!(based.generator().neiif.template_basis, 5);
    let basis = field_of(&based).template.unwrap().basis.unwrap();
    assert_eq!(basis.planes.val().dims(), [5, 3 * 16 * 16 * 4]);
    assert_eq!(
        basis.coefficients.weight.val().dims(),
        [5, based.generator().mapping.w_dim]
    );
    assert_ne!(
        based.shapes(),
        planes.shapes(),
        "a resume must match the basis"
    );
    // The upsampler's kernel: the paper's 1x1 unless asked; 3 reaches the blocks' layers (a
    // neighbourhood of 9 pixels each) and is part of what a resume must match, 1 written out
    // is the default.
    let paper = load(TINY).unwrap();
    assert_eq!(paper.generator().upsampler_kernel, 1);
    let spatial = load(&with_model("upsampler_kernel = 3")).unwrap();
    assert_eq!(spatial.generator().upsampler_kernel, 3);
    let g = spatial
        .generator()
        .init(&burn::tensor::Device::flex())
        .unwrap();
    let block = &g.upsampler.blocks[0];
    assert_eq!(block.kernel(), 3);
    assert_eq!(
        block.conv2.weight.dims(),
        [
            4 * spatial.generator().upsampler_channels,
            9 * spatial.generator().upsampler_channels
        ]
    );
    assert_ne!(
        spatial.shapes(),
        paper.shapes(),
        "a resume must match the kernel"
    );
    let written = load(&with_model("upsampler_kernel = 1")).unwrap();
    assert_eq!(written.shapes(), paper.shapes());
    // The upsampler's noise: none unless asked; 2 octaves give every block a gain layer to
    // 2 C gains, part of what a resume must match; 0 written out is the default.
    assert_eq!(paper.generator().upsampler_noise, 0);
    let noised = load(&with_model("upsampler_noise = 2")).unwrap();
    let g = noised
        .generator()
        .init(&burn::tensor::Device::flex())
        .unwrap();
    assert_eq!(g.upsampler.noise_octaves(), 2);
    let channels = noised.generator().upsampler_channels;
    assert!(g.upsampler.blocks.iter().all(|b| {
        b.noise
            .as_ref()
            .is_some_and(|n| n.gain.weight.dims() == [2 * channels, channels])
    }));
    assert_ne!(
        noised.shapes(),
        paper.shapes(),
        "a resume must match the noise"
    );
    let written = load(&with_model("upsampler_noise = 0")).unwrap();
    assert_eq!(written.shapes(), paper.shapes());
    // The encoding: the paper's unless asked; part of what a resume must match.
    assert!(!load(TINY).unwrap().generator().neiif.rotated_encoding);
    for (key, rotated) in [("axis-aligned", false), ("rotated", true)] {
        let text = with_model(&format!("encoding = \"{key}\""));
        let c = load(&text).unwrap();
        assert_eq!(c.generator().neiif.rotated_encoding, rotated);
        assert_eq!(c.shapes() == load(TINY).unwrap().shapes(), !rotated);
    }
    // Both change the networks' shapes, so a resumed run must match them.
    let shapes = c.shapes();
    for key in [
        "mapping_layers = 2",
        "d_channel_base = 4096",
        "d_channel_max = 256",
    ] {
        assert!(shapes.contains(key), "{shapes}");
    }
}

#[test]
fn bad_configs_name_the_file_and_the_key() {
    let cases = [
        (
            TINY.replace("batch = 4", "batch = 4\nbatchsize = 2"),
            "batchsize",
        ),
        (TINY.replace("batch = 4", "batch = \"four\""), "batch"),
        (TINY.replace("batch = 4", "batch = 6"), "train.batch = 6"),
        (TINY.replace("batch = 4", "lr_g = -1.0"), "train.lr_g"),
        (TINY.replace("batch = 4", "beta2 = 1.0"), "train.beta2"),
        (
            TINY.replace("batch = 4", "batch = 1000000000000"),
            "train.batch = 1000000000000 must be in 1..=1024",
        ),
        (TINY.replace("\"small\"", "\"huge\""), "model.preset"),
        (with_model("sphere_radius = 2.0"), "model.sphere_radius"),
        (with_model("frequencies = 0"), "model.frequencies"),
        (with_model("shading = \"surfaces\""), "shading"),
        (with_model("encoding = \"rotate\""), "encoding"),
        (
            with_model("volume_resolution = 128"),
            "model.volume_resolution = 128",
        ),
        (
            with_model("volume_resolution = 48"),
            "output_resolution 64 must be volume_resolution 48 times a power of two",
        ),
        (
            with_model("volume_resolution = 16"),
            "data.volume_resolution = 32 must equal",
        ),
        (with_model("mapping_layers = 0"), "model.mapping_layers = 0"),
        (with_model("d_channel_base = 0"), "model.d_channel_base = 0"),
        (
            with_model("d_channel_max = 100000"),
            "model.d_channel_max = 100000",
        ),
        (
            TINY.replace("resolution = 64", "resolution = 128"),
            "data.resolution",
        ),
        (format!("{TINY}\n[loss]\nphoto = -0.5\n"), "loss.photo"),
        (format!("{TINY}\n[loss]\nphotos = 0.5\n"), "photos"),
        (
            format!("{TINY}\n[schedule]\nstage1_kimg = 1.0\nfade_kimg = 2.0\n"),
            "fade_kimg",
        ),
        (
            with_model("frequencies = 4")
                + "\n[schedule]\nopen_octaves = 5\noctave_fade_kimg = 1.0\n",
            "schedule.open_octaves = 5",
        ),
        (
            format!("{TINY}\n[schedule]\nopen_octaves = 3\noctave_fade_start_kimg = -1.0\n"),
            "schedule.octave_fade_start_kimg",
        ),
        (
            with_model("template_resolution = 1"),
            "model.template_resolution = 1",
        ),
        (
            with_model("template_resolution = 8\ntemplate_channels = 0"),
            "model.template_channels = 0",
        ),
        (
            with_model("template_bound = 0.0"),
            "model.template_bound = 0.0",
        ),
        (
            with_model("template_bound = nan"),
            "model.template_bound = NaN",
        ),
        (
            with_model("template_bound = 5.0"),
            "model.template_bound = 5.0",
        ),
        (
            with_model("template_resolution = 8\ntemplate_basis = 65"),
            "model.template_basis = 65",
        ),
        (
            with_model("template_basis = 2"),
            "model.template_basis = 2 needs template planes",
        ),
        (
            with_model("upsampler_kernel = 2"),
            "model.upsampler_kernel = 2 must be 1 or 3",
        ),
        (
            with_model("upsampler_kernel = 5"),
            "model.upsampler_kernel = 5",
        ),
        (
            with_model("upsampler_noise = 5"),
            "model.upsampler_noise = 5 must be at most 4 octaves",
        ),
        (format!("{TINY}\n[output]\nkeep = 0\n"), "output.keep"),
        (
            format!("{TINY}\n[data.source]\nkind = \"synthetic\"\nidentity = 3\n"),
            "identity",
        ),
        (TINY.replace("[model]\npreset = \"small\"", ""), "model"),
        (with_model("refine = 8"), "refine = 8"),
        (
            with_model("proposal = 32\nimportance = 0"),
            "importance = 0",
        ),
        (
            with_model("proposal = 32\nimportance = 1"),
            "model.importance = 1",
        ),
        (with_model("proposal = 100000"), "model.proposal = 100000"),
        (with_model("stratified = 0"), "model.stratified = 0"),
        // Values that overflow f32 (every step was skipped as NaN, no cause named), a
        // prefetch that aborted on allocation, and poses that turn the camera over.
        (
            with_model("sphere_prior = 1e308"),
            "model.sphere_prior = 1e308 must",
        ),
        (
            TINY.replace("batch = 4", "r1_gamma = 1e308"),
            "train.r1_gamma = 1e308 must",
        ),
        (
            TINY.replace("batch = 4", "lr_d = 1e308"),
            "train.lr_d = 1e308 must",
        ),
        (
            format!("{TINY}\n[loss]\nalbedo = 1e308\n"),
            "loss.albedo = 1e308 must",
        ),
        (
            format!(
                "{TINY}\n[output]\ngrid_seeds = [{}]\n",
                (0..65)
                    .map(|s| s.to_string())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
            "output.grid_seeds names 65 seeds: give 1 to 64",
        ),
        (
            TINY.replace("batch = 4", "prefetch = 1000000000000"),
            "train.prefetch = 1000000000000 must be in 0..=16",
        ),
        (
            TINY.replace(
                "batch = 4",
                "batch = 4\n[train.pose_prior]\npitch_sd = 1e308",
            ),
            "train.pose_prior.pitch_mean = 0.0 and pitch_sd = 1e308 draw",
        ),
        (
            format!(
                "{TINY}\n[data.source]\nkind = \"synthetic\"\n[data.source.poses]\npitch_mean = 1.5\n"
            ),
            "source.poses.pitch_mean = 1.5",
        ),
    ];
    for (text, key) in cases {
        let e = load(&text).expect_err(key);
        assert!(e.contains("run.toml"), "{e}");
        assert!(e.contains(key), "expected `{key}` in: {e}");
    }
}

/// The resolved config names every key, and loads back to the same config, for the
/// shipped configs and for one that leaves nearly everything to the defaults.
#[test]
fn the_resolved_config_fills_in_every_default_and_loads_back_the_same() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../configs");
    let mut configs: Vec<TrainConfig> = [
        "quickstart.toml",
        "synthetic2h.toml",
        "synthetic-volume64.toml",
        "synthetic64.toml",
    ]
    .iter()
    .map(|name| TrainConfig::load(&root.join(name)).unwrap())
    .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("run.toml");
    configs.push(TrainConfig::from_text(TINY.to_string(), &path).unwrap());
    for config in configs {
        let text = config.resolved();
        for key in [
            "lr_g",
            "r1_gamma",
            "ema_rampup",
            "fade_kimg",
            "geometry",
            "eval_samples",
            "volume_resolution",
            "identities",
            "procedural_height",
            "turbidity",
        ] {
            assert!(text.contains(key), "{key} missing from:\n{text}");
        }
        let again = TrainConfig::from_text(text.clone(), &config.path).unwrap();
        assert_eq!(again.model, config.model);
        assert_eq!(again.train, config.train);
        assert_eq!(again.schedule, config.schedule);
        assert_eq!(again.loss, config.loss);
        assert_eq!(again.output, config.output);
        assert_eq!(again.data, config.data, "{text}");
        assert_eq!(again.resolved(), text);
    }
}
