use volux_envmap::*;
use std::time::Instant;
fn main() {
    let map = io::load(std::path::Path::new("assets/hdri/sunrise.exr")).unwrap();
    let opts = PreconvolveOptions::default();
    for _ in 0..2 {
        let t = Instant::now(); let plans = opts.plans(); println!("plans {:?}", t.elapsed());
        let lmax = plans.iter().map(|p| p.band_limit).max().unwrap();
        let t = Instant::now(); let c = sh::analyse(&map, lmax, 2e-5); println!("analyse L={lmax} {:?}", t.elapsed());
        for p in &plans { let t = Instant::now(); let _ = sh::synthesise(&c, &p.coefficients, p.height); println!("synth n={} {}x{} {:?}", p.exponent, p.width(), p.height, t.elapsed()); }
    }
}
