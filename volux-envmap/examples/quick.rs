use volux_envmap::*;
fn main() {
    let names: Vec<String> = std::env::args().skip(1).collect();
    let tol: f64 = std::env::var("TOL").ok().and_then(|s| s.parse().ok()).unwrap_or(2e-3);
    let maps: Vec<(String, EnvMap)> = names.iter().map(|n| (n.clone(), io::load(std::path::Path::new(&format!("assets/hdri/{n}.exr"))).unwrap())).collect();
    let settings = report::BenchSettings { tolerances: vec![tol], tapers: vec![0.0, 0.5], directions: 1024, texels: 64, repeats: 3, ..Default::default() };
    let r = report::run(&maps, &settings, |l| eprintln!("{l}")).unwrap();
    println!("{}", r.to_markdown());
}
