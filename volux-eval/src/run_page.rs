//! `volux report RUN`: one self-contained HTML page that shows a run, the way a results page
//! shows a StyleGAN or EG3D run. Everything is inline (images and videos as `data:` URIs, no
//! script or style from elsewhere), so the file opens offline, can be mailed, and survives the
//! run folder being moved.
//!
//! What the page holds, each section only when the run has it: the newest checkpoint's state
//! (step, images, wall time, skipped steps), the loss and score curves against images and
//! minutes (`volux plot`'s PNGs, written to `RUN/plots/` on the way), the latest light
//! evaluation against the data's own scores, the table and figures of a `volux eval --out
//! RUN/eval`, the sample grids over time (up to
//! [`MAX_GRIDS`], evenly spaced, the first and the last included), every GIF, MP4 and PNG a
//! `volux sample --out RUN/samples` left, and the config the run was trained with.
//!
//! A small inline script checks the page once loaded: it counts the images that decoded and
//! records any script error in `body` attributes (`data-images`, `data-errors`), which the
//! browser test reads.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use base64::Engine;
use volux_train::checkpoint::{self, TrainState};
use volux_train::run_folder::{GRIDS, METRICS};

use crate::plot::{PlotError, RunMetrics, plot_metrics};

/// Most sample grids shown.
pub const MAX_GRIDS: usize = 8;

/// Where `volux sample` output is looked for in a run folder.
pub const SAMPLES: &str = "samples";

/// Where `volux eval` output (`eval.txt` and its figures) is looked for in a run folder.
pub const EVAL: &str = "eval";

/// Why a report cannot be made.
#[derive(Debug, thiserror::Error)]
pub enum RunPageError {
    #[error("{path}: not a run folder (no {METRICS}, no checkpoint)")]
    NotARun { path: PathBuf },
    #[error("reading {path}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("plotting the curves")]
    Plot(#[from] PlotError),
    #[error("the newest checkpoint")]
    Checkpoint(#[from] checkpoint::CheckpointError),
    #[error("writing {path}")]
    Write {
        path: PathBuf,
        #[source]
        source: volux_envmap::durable::FileError,
    },
}

fn read(path: &Path) -> Result<Vec<u8>, RunPageError> {
    std::fs::read(path).map_err(|source| RunPageError::Read {
        path: path.to_path_buf(),
        source,
    })
}

/// `text` safe inside HTML elements and attribute values.
pub fn escape(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            c => out.push(c),
        }
    }
    out
}

fn data_uri(mime: &str, bytes: &[u8]) -> String {
    format!(
        "data:{mime};base64,{}",
        base64::engine::general_purpose::STANDARD.encode(bytes)
    )
}

/// Files in `folder` with one of `extensions`, sorted by name; none if it does not exist.
fn files(folder: &Path, extensions: &[&str]) -> Vec<PathBuf> {
    let Ok(entries) = std::fs::read_dir(folder) else {
        return Vec::new();
    };
    let mut found: Vec<PathBuf> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            p.is_file()
                && p.extension()
                    .and_then(|e| e.to_str())
                    .is_some_and(|e| extensions.contains(&e.to_ascii_lowercase().as_str()))
        })
        .collect();
    found.sort();
    found
}

/// Up to `most` of `items`, evenly spaced, the first and the last included.
pub fn evenly<T: Clone>(items: &[T], most: usize) -> Vec<T> {
    if items.len() <= most || most < 2 {
        return items.iter().take(most.max(1)).cloned().collect();
    }
    (0..most)
        .map(|i| items[i * (items.len() - 1) / (most - 1)].clone())
        .collect()
}

/// What a grid file's name says: the image count it was drawn at (`grid-<images>.png`).
fn grid_images(path: &Path) -> Option<u64> {
    path.file_stem()?
        .to_str()?
        .strip_prefix("grid-")?
        .parse()
        .ok()
}

fn section(html: &mut String, title: &str) {
    let _ = writeln!(html, "<h2>{}</h2>", escape(title));
}

fn figure(html: &mut String, src: &str, caption: &str, width: Option<usize>) {
    let style = width.map_or(String::new(), |w| format!(" style=\"max-width:{w}px\""));
    let _ = writeln!(
        html,
        "<figure><img src=\"{src}\" alt=\"{c}\"{style}><figcaption>{c}</figcaption></figure>",
        c = escape(caption)
    );
}

/// The eval table: each score beside the data's own (`_floor` or `_data`).
fn eval_table(html: &mut String, values: &std::collections::BTreeMap<String, f64>) {
    html.push_str("<table><tr><th>score</th><th>model</th><th>data</th></tr>\n");
    for (name, value) in values {
        if name.ends_with("_floor") || name.ends_with("_data") {
            continue;
        }
        let reference = values
            .get(&format!("{name}_floor"))
            .or_else(|| values.get(&format!("{name}_data")))
            .map_or("-".to_string(), |r| format!("{r:.3}"));
        let _ = writeln!(
            html,
            "<tr><td>{}</td><td>{value:.3}</td><td>{reference}</td></tr>",
            escape(name)
        );
    }
    html.push_str("</table>\n");
}

const STYLE: &str = "body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 1em;color:#222}\
figure{display:inline-block;margin:0.5em;vertical-align:top}figcaption{font-size:0.85em;color:#555}\
img,video{max-width:100%;image-rendering:pixelated}table{border-collapse:collapse}\
td,th{border:1px solid #ccc;padding:0.2em 0.6em;text-align:right}td:first-child{text-align:left}\
pre{background:#f4f4f4;padding:1em;overflow-x:auto}";

/// Counts decoded images and records script errors in `body` attributes once the page loads.
const CHECK: &str = "<script>\
var volux_errors=0;window.addEventListener('error',function(){volux_errors++;document.body.setAttribute('data-errors',volux_errors);},true);\
window.addEventListener('load',function(){var imgs=document.images,ok=0;\
for(var i=0;i<imgs.length;i++){if(imgs[i].complete&&imgs[i].naturalWidth>0)ok++;}\
document.body.setAttribute('data-images',ok+'/'+imgs.length);\
document.body.setAttribute('data-errors',volux_errors);});</script>";

/// Builds the page of the run in `run`; writes `RUN/plots/` on the way (`volux plot`).
pub fn run_page(run: &Path, title: &str) -> Result<String, RunPageError> {
    let metrics_path = run.join(METRICS);
    let newest = checkpoint::latest(run).ok();
    if !metrics_path.is_file() && newest.is_none() {
        return Err(RunPageError::NotARun {
            path: run.to_path_buf(),
        });
    }
    let state: Option<TrainState> = newest.as_deref().map(checkpoint::read_state).transpose()?;
    let mut html = String::new();
    let _ = write!(
        html,
        "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\"><title>{t}</title><style>{STYLE}</style></head>\n<body data-images=\"loading\" data-errors=\"0\">\n<h1>{t}</h1>\n",
        t = escape(title)
    );
    if let Some(state) = &state {
        section(&mut html, "State");
        let _ = writeln!(
            html,
            "<p>Newest checkpoint: step {}, {:.2} kimg, {:.1} minutes of training, {} skipped \
             non-finite steps, seed {}, discriminators {}.</p>",
            state.step,
            state.images as f64 / 1000.0,
            state.seconds / 60.0,
            state.skipped,
            state.seed,
            escape(&state.discriminators.join(", "))
        );
    }
    if metrics_path.is_file() {
        let metrics = RunMetrics::read(&metrics_path)?;
        section(&mut html, "Curves");
        for png in plot_metrics(&metrics, &run.join("plots"), title)? {
            let caption = match png.file_stem().and_then(|s| s.to_str()) {
                Some("curves-minutes") => "losses and scores against wall-clock minutes",
                _ => "losses and scores against thousands of images",
            };
            figure(
                &mut html,
                &data_uri("image/png", &read(&png)?),
                caption,
                None,
            );
        }
        if let Some(last) = metrics.evals.last() {
            section(&mut html, "Latest light evaluation");
            let _ = writeln!(
                html,
                "<p>At {:.2} kimg{} (the in-training evaluation, <code>[output] eval_kimg</code>; \
                 <code>volux eval</code> measures more samples).</p>",
                last.kimg,
                last.minutes
                    .map_or(String::new(), |m| format!(", {m:.1} minutes"))
            );
            eval_table(&mut html, &last.values);
        }
    }
    let eval = run.join(EVAL);
    let table = eval.join("eval.txt");
    if table.is_file() {
        section(&mut html, "Evaluation");
        let text = String::from_utf8_lossy(&read(&table)?).into_owned();
        let _ = writeln!(
            html,
            "<p><code>volux eval --out RUN/{EVAL}</code>:</p>\n<pre>{}</pre>",
            escape(&text)
        );
        for png in files(&eval, &["png"]) {
            let name = png
                .file_stem()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            figure(&mut html, &data_uri("image/png", &read(&png)?), &name, None);
        }
    }
    let grids: Vec<PathBuf> = files(&run.join(GRIDS), &["png"])
        .into_iter()
        .filter(|p| grid_images(p).is_some())
        .collect();
    if !grids.is_empty() {
        section(&mut html, "Sample grids over training");
        html.push_str(
            "<p>Rows: seeds; columns: albedo, normals, diffuse, specular, relit, depth.</p>\n",
        );
        for grid in evenly(&grids, MAX_GRIDS) {
            let kimg = grid_images(&grid).unwrap_or(0) as f64 / 1000.0;
            figure(
                &mut html,
                &data_uri("image/png", &read(&grid)?),
                &format!("{kimg:.2} kimg"),
                Some(320),
            );
        }
    }
    let samples = run.join(SAMPLES);
    let media = files(&samples, &["png", "gif", "mp4"]);
    if !media.is_empty() {
        section(&mut html, "Samples");
        for file in media {
            let name = file
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default();
            let bytes = read(&file)?;
            match file.extension().and_then(|e| e.to_str()) {
                Some("mp4") => {
                    let _ = writeln!(
                        html,
                        "<figure><video controls loop muted autoplay playsinline src=\"{}\"></video><figcaption>{}</figcaption></figure>",
                        data_uri("video/mp4", &bytes),
                        escape(&name)
                    );
                }
                Some("gif") => figure(&mut html, &data_uri("image/gif", &bytes), &name, None),
                _ => figure(&mut html, &data_uri("image/png", &bytes), &name, None),
            }
        }
    }
    if let Some(state) = &state {
        section(&mut html, "Config");
        let _ = writeln!(
            html,
            "<p>From <code>{}</code>, as the run was started:</p>\n<pre>{}</pre>",
            escape(&state.config_path.display().to_string()),
            escape(&state.config)
        );
    }
    html.push_str(CHECK);
    html.push_str("\n</body></html>\n");
    Ok(html)
}

/// Writes [`run_page`] to `out`, atomically.
pub fn save_run_page(run: &Path, title: &str, out: &Path) -> Result<(), RunPageError> {
    let html = run_page(run, title)?;
    use volux_envmap::durable::{FileError, write_atomically};
    write_atomically(out, |tmp| {
        std::fs::write(tmp, html.as_bytes()).map_err(FileError::at(tmp))
    })
    .map_err(|source| RunPageError::Write {
        path: out.to_path_buf(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn evenly_keeps_the_ends_and_at_most_the_count() {
        let v: Vec<u32> = (0..20).collect();
        assert_eq!(evenly(&v, 5), [0, 4, 9, 14, 19]);
        assert_eq!(evenly(&v[..3], 8), [0, 1, 2]);
        assert_eq!(evenly(&v, 1), [0]);
    }

    #[test]
    fn text_is_escaped() {
        assert_eq!(
            escape("<a href=\"x\">&'</a>"),
            "&lt;a href=&quot;x&quot;&gt;&amp;&#39;&lt;/a&gt;"
        );
    }

    #[test]
    fn a_folder_that_is_no_run_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let e = run_page(dir.path(), "x").unwrap_err().to_string();
        assert!(e.contains("not a run folder"), "{e}");
    }
}
