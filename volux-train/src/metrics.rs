//! The metrics log: one JSON object per line (`metrics.jsonl`): one line per group of steps,
//! with the losses averaged over the group, and one per light evaluation of the EMA generator
//! (`[output] eval_kimg`), which holds an `eval` object instead of `losses`.

use std::collections::BTreeMap;
use std::fs::{self, File, OpenOptions};
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use serde::Serialize;
use volux_model::generator::Generator;

/// An error of a [`ProgressEvaluator`], kept whole for the chain of causes.
pub use volux_envmap::error::BoxError;

/// A measurement of the EMA generator taken during training, every `[output] eval_kimg`
/// thousand images (volux-eval's progress evaluation implements it; training only calls it).
pub trait ProgressEvaluator {
    /// Named scores of `ema`, written under `eval` in metrics.jsonl.
    fn measure(&mut self, ema: &Generator) -> Result<BTreeMap<String, f64>, BoxError>;
}

/// One line of the log.
#[derive(Clone, Debug, Serialize)]
pub struct MetricsLine {
    pub step: u64,
    pub images: u64,
    pub kimg: f64,
    /// Wall-clock minutes the run has trained so far (over all its invocations).
    pub minutes: f64,
    /// The stage the group's last step trained in (1 or 2).
    pub stage: u8,
    pub fade: Vec<f64>,
    /// Wall-clock seconds per step over the group.
    pub sec_per_step: f64,
    pub images_per_sec: f64,
    /// Non-finite steps skipped so far.
    pub skipped: u64,
    /// Peak resident memory of the process so far, in MiB (where the OS reports it).
    pub peak_rss_mib: Option<f64>,
    pub losses: BTreeMap<String, f64>,
}

/// One light evaluation of the EMA generator.
#[derive(Clone, Debug, Serialize)]
pub struct EvalLine {
    pub step: u64,
    pub images: u64,
    pub kimg: f64,
    /// Wall-clock minutes the run had trained when the evaluation started.
    pub minutes: f64,
    /// What the evaluation itself cost.
    pub eval_seconds: f64,
    pub eval: BTreeMap<String, f64>,
}

/// Averages of loss terms over a group of steps.
#[derive(Clone, Debug, Default)]
pub struct Averages {
    sums: BTreeMap<String, (f64, u32)>,
}

impl Averages {
    pub fn add(&mut self, losses: &BTreeMap<&'static str, f64>) {
        for (k, v) in losses {
            let e = self.sums.entry(k.to_string()).or_insert((0.0, 0));
            e.0 += v;
            e.1 += 1;
        }
    }

    /// The averages, emptying the accumulator.
    pub fn take(&mut self) -> BTreeMap<String, f64> {
        std::mem::take(&mut self.sums)
            .into_iter()
            .map(|(k, (s, n))| (k, s / n as f64))
            .collect()
    }
}

/// Median of a list (0 when empty).
pub fn median(values: &[f64]) -> f64 {
    if values.is_empty() {
        return 0.0;
    }
    let mut v = values.to_vec();
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Appends lines to `metrics.jsonl`.
pub struct MetricsLog {
    path: PathBuf,
    file: File,
}

impl MetricsLog {
    /// Opens `path` for appending, first dropping lines after `step` (left by a run that went
    /// on past its last checkpoint before it stopped).
    pub fn open(path: &Path, after_step: u64) -> std::io::Result<MetricsLog> {
        if path.exists() {
            let kept: Vec<String> = BufReader::new(File::open(path)?)
                .lines()
                .map_while(Result::ok)
                .filter(|line| {
                    serde_json::from_str::<serde_json::Value>(line)
                        .ok()
                        .and_then(|v| v.get("step")?.as_u64())
                        .is_some_and(|s| s <= after_step)
                })
                .collect();
            let mut text = kept.join("\n");
            if !text.is_empty() {
                text.push('\n');
            }
            fs::write(path, text)?;
        }
        let file = OpenOptions::new().create(true).append(true).open(path)?;
        Ok(MetricsLog {
            path: path.to_path_buf(),
            file,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn write(&mut self, line: &impl Serialize) -> std::io::Result<()> {
        let text = serde_json::to_string(line).map_err(std::io::Error::other)?;
        writeln!(self.file, "{text}")?;
        self.file.flush()
    }
}

/// Peak resident set size of this process in MiB (Linux: `VmHWM` in `/proc/self/status`).
pub fn peak_rss_mib() -> Option<f64> {
    let status = fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    let kib: f64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib / 1024.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(step: u64) -> MetricsLine {
        MetricsLine {
            step,
            images: step * 4,
            kimg: step as f64 * 0.004,
            minutes: step as f64 / 60.0,
            stage: 1,
            fade: vec![0.5],
            sec_per_step: 1.0,
            images_per_sec: 4.0,
            skipped: 0,
            peak_rss_mib: None,
            losses: [("G_total".to_string(), 0.7)].into(),
        }
    }

    #[test]
    fn reopening_drops_lines_past_the_checkpoint() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("metrics.jsonl");
        let mut log = MetricsLog::open(&path, 0).unwrap();
        for s in [10, 20, 30] {
            log.write(&line(s)).unwrap();
        }
        drop(log);
        let mut log = MetricsLog::open(&path, 20).unwrap();
        log.write(&line(30)).unwrap();
        let text = fs::read_to_string(&path).unwrap();
        let steps: Vec<u64> = text
            .lines()
            .map(|l| {
                serde_json::from_str::<serde_json::Value>(l).unwrap()["step"]
                    .as_u64()
                    .unwrap()
            })
            .collect();
        assert_eq!(steps, vec![10, 20, 30]);
        let mut a = Averages::default();
        a.add(&[("x", 1.0)].into());
        a.add(&[("x", 3.0)].into());
        assert_eq!(a.take()["x"], 2.0);
        assert!(a.take().is_empty());
    }
}
