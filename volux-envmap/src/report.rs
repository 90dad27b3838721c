//! Error against run time of the fast preconvolution, measured against [`crate::reference`].
//!
//! For each map, exponent, tolerance and taper: the band limit and light-map size the plan
//! chose, the wall time, and the relative errors against the f64 reference measured two ways:
//! - at uniformly random directions through the bilinear look-up, which is what shading sees
//!   (a light map that is too coarse shows here);
//! - at random texel centres of the light map (the convolution itself, without look-up error).
//!
//! `rel RMS = sqrt(sum (fast - ref)^2 / sum ref^2)` over all samples and channels;
//! `max rel = max |fast - ref| / max(ref, 1% of the RMS of ref)` (the floor keeps black
//! regions of a map from turning round-off into huge ratios).

use std::fmt::Write as _;
use std::time::Instant;

use crate::direction::{self, Dir};
use crate::envmap::{EnvMap, Rgb};
use crate::error::EnvMapError;
use crate::lightmap::LightMap;
use crate::preconvolve::{PreconvolveOptions, preconvolve};
use crate::random::SplitMix64;
use crate::reference::Reference;

/// Relative errors of a set of samples.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct ErrorStats {
    pub rel_rms: f64,
    pub max_rel: f64,
}

/// Errors of `fast` against `reference` (same length), as defined in the module docs.
pub fn compare(fast: &[Rgb], reference: &[[f64; 3]]) -> ErrorStats {
    assert_eq!(fast.len(), reference.len());
    let (mut err2, mut ref2) = (0.0f64, 0.0f64);
    for (f, r) in fast.iter().zip(reference) {
        for c in 0..3 {
            err2 += (f64::from(f[c]) - r[c]).powi(2);
            ref2 += r[c] * r[c];
        }
    }
    if ref2 == 0.0 {
        return ErrorStats {
            rel_rms: if err2 == 0.0 { 0.0 } else { f64::INFINITY },
            max_rel: if err2 == 0.0 { 0.0 } else { f64::INFINITY },
        };
    }
    let floor = 0.01 * (ref2 / (3 * reference.len()) as f64).sqrt();
    let max_rel = fast
        .iter()
        .zip(reference)
        .flat_map(|(f, r)| (0..3).map(move |c| (f64::from(f[c]) - r[c]).abs() / r[c].max(floor)))
        .fold(0.0, f64::max);
    ErrorStats {
        rel_rms: (err2 / ref2).sqrt(),
        max_rel,
    }
}

/// `count` directions uniform on the sphere.
pub fn random_directions(count: usize, seed: u64) -> Vec<Dir> {
    let mut rng = SplitMix64::new(seed);
    (0..count)
        .map(|_| {
            let y = 2.0 * rng.next_f64() - 1.0;
            let phi = std::f64::consts::TAU * rng.next_f64();
            let r = (1.0 - y * y).max(0.0).sqrt();
            [r * phi.sin(), y, r * phi.cos()]
        })
        .collect()
}

/// Errors of one light map against its reference: at `dirs` through the look-up (with the
/// reference values there given), and at `texels` random texel centres.
pub fn measure(
    map: &LightMap,
    reference: &Reference,
    dirs: &[Dir],
    reference_at_dirs: &[[f64; 3]],
    texels: usize,
    seed: u64,
) -> (ErrorStats, ErrorStats) {
    let looked_up: Vec<Rgb> = dirs.iter().map(|d| map.lookup(*d)).collect();
    let random = compare(&looked_up, reference_at_dirs);
    let mut rng = SplitMix64::new(seed);
    let (w, h) = (map.width(), map.height());
    let picks: Vec<usize> = (0..texels)
        .map(|_| (rng.next_u64() % (w * h) as u64) as usize)
        .collect();
    let centres: Vec<Dir> = picks
        .iter()
        .map(|&i| direction::texel_dir(i % w, i / w, w, h))
        .collect();
    let stored: Vec<Rgb> = picks.iter().map(|&i| map.texels()[i]).collect();
    let at_centres = compare(&stored, &reference.eval_many(&centres));
    (random, at_centres)
}

/// What to measure.
#[derive(Clone, Debug)]
pub struct BenchSettings {
    pub exponents: Vec<u32>,
    pub tolerances: Vec<f64>,
    pub tapers: Vec<f64>,
    /// Random directions per (map, exponent), looked up bilinearly.
    pub directions: usize,
    /// Random texel centres per light map.
    pub texels: usize,
    /// Timing runs per setting; the fastest is reported.
    pub repeats: usize,
}

impl Default for BenchSettings {
    fn default() -> Self {
        Self {
            exponents: crate::DEFAULT_EXPONENTS.to_vec(),
            tolerances: vec![1e-2, 5e-3, 2e-3, 1e-3, 5e-4],
            tapers: vec![0.0, crate::preconvolve::DEFAULT_TAPER],
            directions: 2048,
            texels: 256,
            repeats: 3,
        }
    }
}

/// One lobe at one setting.
#[derive(Clone, Debug)]
pub struct LobeRow {
    pub map: String,
    pub exponent: u32,
    pub tolerance: f64,
    pub taper: f64,
    pub band_limit: usize,
    pub width: usize,
    pub height: usize,
    /// Wall time of this lobe alone (its own analysis included), seconds.
    pub seconds: f64,
    pub random: ErrorStats,
    pub texel: ErrorStats,
    /// Fraction of the light map's values that rang negative and were clamped.
    pub clamped_fraction: f64,
}

/// All lobes of one map at one setting, computed together as `preconvolve` does.
#[derive(Clone, Debug)]
pub struct SetRow {
    pub map: String,
    pub tolerance: f64,
    pub taper: f64,
    /// Fastest wall time, seconds (lobe plans cached from earlier runs).
    pub seconds: f64,
    /// Wall time of the first run, planning the lobes included, seconds.
    pub first_seconds: f64,
    /// Worst relative RMS error at random directions over the lobes.
    pub worst_rel_rms: f64,
}

/// The whole measurement.
#[derive(Clone, Debug, Default)]
pub struct BenchReport {
    pub lobes: Vec<LobeRow>,
    pub sets: Vec<SetRow>,
    /// Seconds the f64 reference took per (map, exponent) at the random directions.
    pub reference_seconds: Vec<(String, u32, f64)>,
}

/// Runs `f` `repeats` times: its last result, the fastest time and the first time (seconds).
fn time_best<T>(repeats: usize, mut f: impl FnMut() -> T) -> (T, f64, f64) {
    let mut best = f64::INFINITY;
    let mut first = None;
    let mut out = None;
    for _ in 0..repeats.max(1) {
        let t = Instant::now();
        let v = f();
        let secs = t.elapsed().as_secs_f64();
        best = best.min(secs);
        first.get_or_insert(secs);
        out = Some(v);
    }
    (out.expect("at least one run"), best, first.unwrap_or(best))
}

/// Runs the measurement on named maps, calling `log` with a line per step.
pub fn run(
    maps: &[(String, EnvMap)],
    settings: &BenchSettings,
    mut log: impl FnMut(&str),
) -> Result<BenchReport, EnvMapError> {
    let mut report = BenchReport::default();
    let dirs = random_directions(settings.directions, 0x5EED);
    for (name, map) in maps {
        for &tolerance in &settings.tolerances {
            for &taper in &settings.tapers {
                let options = PreconvolveOptions {
                    exponents: settings.exponents.clone(),
                    tolerance,
                    taper,
                    ..PreconvolveOptions::default()
                };
                options.validate()?;
                let (_, seconds, first_seconds) =
                    time_best(settings.repeats, || preconvolve(map, &options));
                report.sets.push(SetRow {
                    map: name.clone(),
                    tolerance,
                    taper,
                    seconds,
                    first_seconds,
                    worst_rel_rms: 0.0,
                });
            }
        }
        for &n in &settings.exponents {
            let reference = Reference::new(map, n);
            let t = Instant::now();
            let at_dirs = reference.eval_many(&dirs);
            report
                .reference_seconds
                .push((name.clone(), n, t.elapsed().as_secs_f64()));
            for &tolerance in &settings.tolerances {
                for &taper in &settings.tapers {
                    let options = PreconvolveOptions {
                        exponents: vec![n],
                        tolerance,
                        taper,
                        ..PreconvolveOptions::default()
                    };
                    let (set, seconds, _) =
                        time_best(settings.repeats, || preconvolve(map, &options));
                    let set = set?;
                    let lm = &set.maps()[0];
                    let (random, texel) = measure(
                        lm,
                        &reference,
                        &dirs,
                        &at_dirs,
                        settings.texels,
                        u64::from(n),
                    );
                    log(&format!(
                        "{name} n={n} tol={tolerance:e} taper={taper}: {}x{} L={} {:.1} ms, rel RMS {:.3}%",
                        lm.width(),
                        lm.height(),
                        options.plans()[0].band_limit,
                        seconds * 1e3,
                        random.rel_rms * 100.0
                    ));
                    if let Some(set) = report
                        .sets
                        .iter_mut()
                        .find(|s| &s.map == name && s.tolerance == tolerance && s.taper == taper)
                    {
                        set.worst_rel_rms = set.worst_rel_rms.max(random.rel_rms);
                    }
                    report.lobes.push(LobeRow {
                        map: name.clone(),
                        exponent: n,
                        tolerance,
                        taper,
                        band_limit: options.plans()[0].band_limit,
                        width: lm.width(),
                        height: lm.height(),
                        seconds,
                        random,
                        texel,
                        clamped_fraction: lm.clamped() as f64
                            / (3 * lm.width() * lm.height()) as f64,
                    });
                }
            }
        }
    }
    Ok(report)
}

impl BenchReport {
    /// The report as Markdown tables.
    pub fn to_markdown(&self) -> String {
        let mut s = String::new();
        let _ = writeln!(
            s,
            "### All lobes together (what `preconvolve` costs)\n\n\
             | map | tolerance | taper | wall ms | first run ms (planning included) | worst rel RMS (look-up) |\n|---|---|---|---|---|---|"
        );
        for r in &self.sets {
            let _ = writeln!(
                s,
                "| {} | {:.0e} | {} | {:.1} | {:.1} | {:.3}% |",
                r.map,
                r.tolerance,
                r.taper,
                r.seconds * 1e3,
                r.first_seconds * 1e3,
                r.worst_rel_rms * 100.0
            );
        }
        let _ = writeln!(
            s,
            "\n### Per lobe\n\n\
             | map | n | tolerance | taper | L | light map | ms | rel RMS look-up | max rel look-up | rel RMS texels | max rel texels | clamped |\n\
             |---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for r in &self.lobes {
            let _ = writeln!(
                s,
                "| {} | {} | {:.0e} | {} | {} | {}x{} | {:.1} | {:.3}% | {:.2}% | {:.3}% | {:.2}% | {:.2}% |",
                r.map,
                r.exponent,
                r.tolerance,
                r.taper,
                r.band_limit,
                r.width,
                r.height,
                r.seconds * 1e3,
                r.random.rel_rms * 100.0,
                r.random.max_rel * 100.0,
                r.texel.rel_rms * 100.0,
                r.texel.max_rel * 100.0,
                r.clamped_fraction * 100.0
            );
        }
        let _ = writeln!(
            s,
            "\n### f64 reference, for scale\n\n| map | n | seconds for the sample directions |\n|---|---|---|"
        );
        for (map, n, secs) in &self.reference_seconds {
            let _ = writeln!(s, "| {map} | {n} | {secs:.2} |");
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn compare_is_relative_and_floors_black() {
        let r = [[1.0, 2.0, 0.0], [3.0, 0.0, 4.0]];
        let exact: Vec<Rgb> = r.iter().map(|c| c.map(|v| v as f32)).collect();
        assert_eq!(compare(&exact, &r), ErrorStats::default());
        let off: Vec<Rgb> = r.iter().map(|c| c.map(|v| (v * 1.01) as f32)).collect();
        let e = compare(&off, &r);
        assert!((e.rel_rms - 0.01).abs() < 1e-6 && (e.max_rel - 0.01).abs() < 1e-6);
        let mut bumped = exact.clone();
        bumped[0][2] = 1e-3; // reference 0 there: measured against the floor
        assert!(compare(&bumped, &r).max_rel.is_finite());
    }

    #[test]
    fn random_directions_are_unit_and_cover_the_sphere() {
        let d = random_directions(4000, 1);
        assert!(
            d.iter()
                .all(|v| (v[0] * v[0] + v[1] * v[1] + v[2] * v[2] - 1.0).abs() < 1e-12)
        );
        let mean_y: f64 = d.iter().map(|v| v[1]).sum::<f64>() / 4000.0;
        assert!(mean_y.abs() < 0.05);
        assert_eq!(random_directions(3, 7), random_directions(3, 7));
    }
}
