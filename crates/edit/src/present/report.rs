//! The run report: `report.html`, a single self-contained page that opens from disk (no server, no
//! external resources, inline CSS) and links the run's images by relative paths. Apart from the optional
//! interactive 3D viewer (`present::viewer`, WebGL2, its scenes embedded in the page) it needs no
//! JavaScript; one small inline script only reports images that failed to load on the browser console.
//!
//! The editing loop fills a [`ReportData`] (also serialisable into `run.json`) and calls [`write_report`].
//! Paths inside `ReportData` are relative to the output folder the report is written into (absolute
//! paths are accepted and made relative). Files that do not exist when the report is written are shown as
//! "missing" instead of as broken images.
//!
//! The page is written with `maud`'s `html!` templates: markup checked at compile time, and every piece of
//! text from the data (prompts, names, paths, settings) escaped on output.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Component, Path, PathBuf};

use maud::{html, Markup, PreEscaped};
use serde::{Deserialize, Serialize};

use crate::eval::clip_score::ClipDirectionalReport;
use crate::eval::metrics::{ConsistencySummary, PreservationReport};

/// File name of the report inside the output folder.
pub const REPORT_FILE: &str = "report.html";

#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    #[error("{}: cannot write the report: {msg}", .path.display())]
    Write { path: PathBuf, msg: String },
}

/// One view before and after editing.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ViewPair {
    pub name: String,
    /// Render of the source scene.
    pub before: PathBuf,
    /// Render of the edited scene.
    pub after: PathBuf,
}

/// One iteration of the editing loop.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct IterationInfo {
    /// 0-based.
    pub index: usize,
    /// The source prompt used in this iteration (from the second one, the target prompt).
    #[serde(default)]
    pub source_prompt: Option<String>,
    /// Guidance (edited) images, one per view, in view order.
    #[serde(default)]
    pub guidance: Vec<PathBuf>,
    /// Renders of the scene after this iteration's fit (optional).
    #[serde(default)]
    pub renders: Vec<PathBuf>,
    /// Multi-view consistency of the guidance images.
    #[serde(default)]
    pub guidance_consistency: Option<ConsistencySummary>,
    #[serde(default)]
    pub seconds: Option<f64>,
    /// The factor on the geometry rates of this iteration's fit (below 1: the shape was kept).
    #[serde(default)]
    pub geometry_rate: Option<f32>,
    /// Pixels the guidance changed outside the editable footprint, per footprint pixel.
    #[serde(default)]
    pub footprint_change: Option<f64>,
}

/// A per-word attention map image.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct WordImage {
    pub word: String,
    pub path: PathBuf,
}

/// Metrics of one run (every field optional: fill what was computed).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct MetricsSummary {
    /// Consistency of the source scene's own renders: the floor the other numbers compare against.
    #[serde(default)]
    pub source_consistency: Option<ConsistencySummary>,
    /// Consistency of the guidance images of the last iteration.
    #[serde(default)]
    pub guidance_consistency: Option<ConsistencySummary>,
    /// Consistency of the final renders of the edited scene.
    #[serde(default)]
    pub final_consistency: Option<ConsistencySummary>,
    /// Edited vs source renders outside the editable mask.
    #[serde(default)]
    pub preservation_outside_mask: Option<PreservationReport>,
    /// Edited vs source renders, whole images.
    #[serde(default)]
    pub preservation_whole: Option<PreservationReport>,
    #[serde(default)]
    pub clip: Option<ClipDirectionalReport>,
    /// Fraction of the pixels where the edit may act (inside the mask, else whole images) whose colour
    /// changed by more than `metrics::CHANGE_TOLERANCE`: near 0 means the edit did nothing.
    #[serde(default)]
    pub changed_fraction: Option<f64>,
    /// Anything else worth a row (name → value).
    #[serde(default)]
    pub extra: BTreeMap<String, f64>,
}

/// One run in a comparison table (e.g. `--guidance per-view`, `--no-ccm`, default).
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct RunSummary {
    pub name: String,
    pub metrics: MetricsSummary,
    /// That run's own report, if any.
    #[serde(default)]
    pub report: Option<PathBuf>,
}

#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct StageTiming {
    pub stage: String,
    pub seconds: f64,
}

/// Everything the report shows.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ReportData {
    pub title: String,
    pub source_prompt: String,
    pub target_prompt: String,
    /// Input scene and cameras as the user gave them (shown, not linked).
    #[serde(default)]
    pub scene: Option<String>,
    #[serde(default)]
    pub cameras: Option<String>,
    /// The edited scene file (linked).
    #[serde(default)]
    pub edited_scene: Option<PathBuf>,
    /// Settings of the run; top-level keys become table rows.
    #[serde(default)]
    pub settings: serde_json::Value,
    /// Remarks for the reader (e.g. "no LPIPS weights: fitted with L1 + D-SSIM").
    #[serde(default)]
    pub notes: Vec<String>,
    #[serde(default)]
    pub views: Vec<ViewPair>,
    #[serde(default)]
    pub iterations: Vec<IterationInfo>,
    #[serde(default)]
    pub attention: Vec<WordImage>,
    /// Mask images, one per view (or a subset).
    #[serde(default)]
    pub masks: Vec<PathBuf>,
    #[serde(default)]
    pub metrics: MetricsSummary,
    /// Other runs to compare with (this run is not added automatically; include it if wanted).
    #[serde(default)]
    pub runs: Vec<RunSummary>,
    #[serde(default)]
    pub timings: Vec<StageTiming>,
    #[serde(default)]
    pub turntable: Option<PathBuf>,
}

/// Layout choices.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ReportOptions {
    /// Views shown in the before/after grid and per iteration (evenly spaced when there are more).
    pub max_views: usize,
    /// Thumbnail width in CSS pixels.
    pub thumb_px: u32,
}

impl Default for ReportOptions {
    fn default() -> Self {
        Self {
            max_views: 8,
            thumb_px: 200,
        }
    }
}

/// Percent-encodes one path segment for a URL (RFC 3986 unreserved characters stay).
fn encode_segment(seg: &str) -> String {
    let mut out = String::new();
    for b in seg.bytes() {
        if b.is_ascii_alphanumeric() || matches!(b, b'-' | b'.' | b'_' | b'~') {
            out.push(b as char);
        } else {
            let _ = write!(out, "%{b:02X}");
        }
    }
    out
}

/// Lexically normalised absolute form of `p` (relative paths taken against the current directory).
fn absolute(p: &Path) -> PathBuf {
    let joined = if p.is_absolute() {
        p.to_path_buf()
    } else {
        std::env::current_dir().unwrap_or_default().join(p)
    };
    let mut out = PathBuf::new();
    for c in joined.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other),
        }
    }
    out
}

/// `path` (relative to `dir`, or absolute) as a relative path from `dir`.
fn relative_to(dir: &Path, path: &Path) -> PathBuf {
    if !path.is_absolute() {
        return path.to_path_buf();
    }
    let (d, p) = (absolute(dir), absolute(path));
    let dc: Vec<_> = d.components().collect();
    let pc: Vec<_> = p.components().collect();
    let common = dc.iter().zip(&pc).take_while(|(a, b)| a == b).count();
    let mut rel = PathBuf::new();
    for _ in common..dc.len() {
        rel.push("..");
    }
    for c in &pc[common..] {
        rel.push(c.as_os_str());
    }
    rel
}

/// The URL of `path` relative to the report in `dir`.
fn href(dir: &Path, path: &Path) -> String {
    relative_to(dir, path)
        .components()
        .filter_map(|c| match c {
            Component::Normal(s) => Some(encode_segment(&s.to_string_lossy())),
            Component::ParentDir => Some("..".to_string()),
            _ => None,
        })
        .collect::<Vec<_>>()
        .join("/")
}

/// Evenly spaced indices from 0..n, first and last included: all of them when n ≤ max (or max = 0).
pub fn subset_indices(n: usize, max: usize) -> Vec<usize> {
    if n <= max || max == 0 {
        return (0..n).collect();
    }
    if max == 1 {
        return vec![0];
    }
    (0..max).map(|i| i * (n - 1) / (max - 1)).collect()
}

fn fmt_opt(v: Option<f64>, digits: usize) -> String {
    match v {
        Some(x) if x.is_finite() => format!("{x:.digits$}"),
        _ => "–".to_string(),
    }
}

fn fmt_seconds(s: f64) -> String {
    if !s.is_finite() {
        return "–".into();
    }
    if s >= 3600.0 {
        format!(
            "{}h {:02}m",
            (s / 3600.0) as u64,
            ((s % 3600.0) / 60.0) as u64
        )
    } else if s >= 60.0 {
        format!("{}m {:02}s", (s / 60.0) as u64, (s % 60.0) as u64)
    } else {
        format!("{s:.1} s")
    }
}

const CSS: &str = "
:root{--fg:#1d2327;--muted:#5f6b73;--line:#d5dadd;--bg:#fbfbfa;--accent:#2a6f97}
*{box-sizing:border-box}
body{margin:0;padding:24px 32px 48px;font:15px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;color:var(--fg);background:var(--bg);overflow-wrap:break-word}
@media (max-width:600px){body{padding:16px 12px 32px}}
h1{font-size:26px;margin:0 0 6px}
h2{font-size:19px;margin:34px 0 10px;padding-bottom:4px;border-bottom:1px solid var(--line)}
h3{font-size:15px;margin:18px 0 6px;color:var(--muted)}
.prompts{font-size:17px;margin:4px 0 14px}
.prompts .arrow{color:var(--muted);padding:0 8px}
.muted{color:var(--muted)}
.notes{background:#fff6e0;border:1px solid #f0d9a0;padding:8px 12px;border-radius:6px;margin:10px 0}
table{border-collapse:collapse;margin:6px 0 12px;background:#fff;display:block;width:max-content;max-width:100%;overflow-x:auto}
th,td{border:1px solid var(--line);padding:4px 10px;text-align:left;vertical-align:top}
th{background:#f0f2f3;font-weight:600}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:flex;flex-wrap:wrap;gap:10px}
figure{margin:0;background:#fff;border:1px solid var(--line);border-radius:6px;padding:6px;min-width:0;max-width:100%}
img{max-width:100%;height:auto}
figure img{display:block;image-rendering:auto}
figcaption{font-size:12px;color:var(--muted);margin-top:4px;max-width:100%;overflow-wrap:anywhere}
.pair{display:flex;gap:4px}
.pair>*{min-width:0;flex:0 1 auto}
.missing{max-width:100%;display:flex;align-items:center;justify-content:center;background:#eee;color:#a33;font-size:12px;padding:6px;overflow-wrap:anywhere}
.bar{background:var(--accent);height:10px;border-radius:2px}
code{font-size:13px;overflow-wrap:anywhere}
pre.json{margin:0;font-size:12px;white-space:pre-wrap;overflow-wrap:anywhere;max-width:100%}
";

/// The page's only script, optional for reading it: once everything has loaded, images that failed are
/// reported on the browser console (which the headless-browser test watches) and labelled.
const BROKEN_IMAGE_CHECK: &str = "window.addEventListener('load',function(){\
document.querySelectorAll('img').forEach(function(i){\
if(!i.complete||i.naturalWidth===0){console.error('image failed to load: '+i.getAttribute('src'));\
i.alt='missing: '+i.getAttribute('src');}});});";

/// The page's sections, laid out for the output folder `dir` (where the referenced files are looked up).
struct Page<'a> {
    dir: &'a Path,
    opts: &'a ReportOptions,
}

impl Page<'_> {
    /// An image thumbnail linking to the full-size file, or a "missing" box.
    fn image(&self, path: &Path, alt: &str, width: u32) -> Markup {
        let resolved = if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.dir.join(path)
        };
        if resolved.is_file() {
            let url = href(self.dir, path);
            html! { a href=(url) { img src=(url) alt=(alt) width=(width); } }
        } else {
            html! {
                div.missing style={ "width:" (width) "px;height:" (width * 3 / 4) "px" } {
                    "missing: " (path.to_string_lossy())
                }
            }
        }
    }

    fn figure(&self, path: &Path, caption: &str, width: u32) -> Markup {
        html! { figure { (self.image(path, caption, width)) figcaption { (caption) } } }
    }

    fn header(&self, d: &ReportData, title: &str) -> Markup {
        let has_facts = d.scene.is_some() || d.cameras.is_some() || d.edited_scene.is_some();
        html! {
            h1 { (title) }
            div.prompts { "“" (d.source_prompt) "”" span.arrow { "→" } "“" (d.target_prompt) "”" }
            @if has_facts {
                p.muted {
                    @if let Some(s) = &d.scene { "scene " code { (s) } }
                    @if let Some(c) = &d.cameras {
                        @if d.scene.is_some() { " · " }
                        "cameras " code { (c) }
                    }
                    @if let Some(e) = &d.edited_scene {
                        @if d.scene.is_some() || d.cameras.is_some() { " · " }
                        "edited scene " a href=(href(self.dir, e)) { code { (e.to_string_lossy()) } }
                    }
                }
            }
            @if !d.notes.is_empty() {
                div.notes { @for n in &d.notes { div { (n) } } }
            }
        }
    }

    fn settings(&self, settings: &serde_json::Value) -> Markup {
        let settings = &tidy_numbers(settings);
        html! {
            @if let Some(map) = settings.as_object() {
                @if !map.is_empty() {
                    h2 { "Settings" }
                    table {
                        @for (k, v) in map {
                            tr {
                                th { (k) }
                                td {
                                    @match v {
                                        serde_json::Value::String(s) => code { (s) },
                                        // Nested settings, indented and wrapped within the page.
                                        serde_json::Value::Object(_) | serde_json::Value::Array(_) => {
                                            pre.json { (serde_json::to_string_pretty(v).unwrap_or_default()) }
                                        }
                                        other => code { (other.to_string()) },
                                    }
                                }
                            }
                        }
                    }
                }
            } @else if !settings.is_null() {
                h2 { "Settings" }
                pre.json { (serde_json::to_string_pretty(settings).unwrap_or_default()) }
            }
        }
    }

    fn turntable(&self, gif: &Option<PathBuf>) -> Markup {
        html! {
            @if let Some(g) = gif {
                h2 { "Turntable" }
                div.grid { (self.figure(g, "edited scene, orbit", self.opts.thumb_px * 2)) }
            }
        }
    }

    fn before_after(&self, views: &[ViewPair]) -> Markup {
        if views.is_empty() {
            return html! {};
        }
        let shown = subset_indices(views.len(), self.opts.max_views);
        let w = self.opts.thumb_px;
        html! {
            h2 { "Before / after" }
            p.muted { (shown.len()) " of " (views.len()) " views; click an image for full size." }
            div.grid {
                @for &i in &shown {
                    @let v = &views[i];
                    figure {
                        div.pair {
                            (self.image(&v.before, &format!("{} before", v.name), w))
                            (self.image(&v.after, &format!("{} after", v.name), w))
                        }
                        figcaption { (v.name) " — source | edited" }
                    }
                }
            }
        }
    }

    fn iterations(&self, iterations: &[IterationInfo]) -> Markup {
        if iterations.is_empty() {
            return html! {};
        }
        let w = self.opts.thumb_px * 3 / 4;
        html! {
            h2 { "Guidance per iteration" }
            @for it in iterations {
                h3 {
                    "Iteration " (it.index + 1)
                    @if let Some(p) = &it.source_prompt { " · source prompt “" (p) "”" }
                    @if let Some(c) = &it.guidance_consistency {
                        " · cross-view error " (fmt_opt(c.mean_abs_error, 4)) " (" (fmt_opt(c.psnr, 2)) " dB)"
                    }
                    @if let Some(s) = it.seconds { " · " (fmt_seconds(s)) }
                    @if let Some(r) = it.geometry_rate.filter(|&r| r < 1.0) { " · shape kept (geometry × " (r) ")" }
                }
                @if it.index > 0 && it.source_prompt.is_some() {
                    p.muted {
                        "This iteration edits renders of the scene the previous one fitted, which already show \
                         the edit, so its source prompt is the target prompt."
                    }
                }
                @for (label, list) in [("guidance", &it.guidance), ("render after fit", &it.renders)] {
                    @if !list.is_empty() {
                        div.grid {
                            @for i in subset_indices(list.len(), self.opts.max_views) {
                                (self.figure(&list[i], &format!("view {i} {label}"), w))
                            }
                        }
                    }
                }
            }
        }
    }

    fn attention(&self, words: &[WordImage], masks: &[PathBuf]) -> Markup {
        if words.is_empty() && masks.is_empty() {
            return html! {};
        }
        let w = self.opts.thumb_px * 3 / 4;
        html! {
            h2 { "Attention and mask" }
            @if !words.is_empty() {
                div.grid { @for wi in words { (self.figure(&wi.path, &format!("“{}”", wi.word), w)) } }
            }
            @if !masks.is_empty() {
                h3 { "Editable mask" }
                div.grid {
                    @for i in subset_indices(masks.len(), self.opts.max_views) {
                        (self.figure(&masks[i], &format!("mask, view {i}"), w))
                    }
                }
            }
        }
    }

    fn metrics(&self, m: &MetricsSummary, runs: &[RunSummary]) -> Markup {
        let rows = metric_rows(m);
        let err =
            |c: &Option<ConsistencySummary>| fmt_opt(c.as_ref().and_then(|c| c.mean_abs_error), 4);
        html! {
            @if !rows.is_empty() {
                h2 { "Metrics" }
                table {
                    tr { th { "metric" } th { "value" } th { "detail" } }
                    @for (name, value, detail) in &rows {
                        tr { td { (name) } td.num { (value) } td.muted { (detail) } }
                    }
                }
                p.muted {
                    "Cross-view error: mean absolute colour difference (0–1 scale) between each view and its \
                     nearest cameras, warped with the scene's rendered depth, over co-visible pixels; lower is \
                     more consistent."
                }
            }
            @if !runs.is_empty() {
                h2 { "Comparison" }
                table {
                    tr {
                        th { "run" } th { "guidance error" } th { "final error" } th { "final PSNR" }
                        th { "PSNR outside" } th { "SSIM outside" } th { "CLIP dir." }
                    }
                    @for r in runs {
                        @let m = &r.metrics;
                        @let pres = m.preservation_outside_mask.as_ref().or(m.preservation_whole.as_ref());
                        tr {
                            td {
                                @match &r.report {
                                    Some(p) => a href=(href(self.dir, p)) { (r.name) },
                                    None => (r.name),
                                }
                            }
                            td.num { (err(&m.guidance_consistency)) }
                            td.num { (err(&m.final_consistency)) }
                            td.num { (fmt_opt(m.final_consistency.as_ref().and_then(|c| c.psnr), 2)) }
                            td.num { (fmt_opt(pres.and_then(|p| p.psnr), 2)) }
                            td.num { (fmt_opt(pres.and_then(|p| p.ssim), 4)) }
                            td.num { (fmt_opt(m.clip.as_ref().map(|c| c.directional), 4)) }
                        }
                    }
                }
            }
        }
    }

    fn timings(&self, timings: &[StageTiming]) -> Markup {
        if timings.is_empty() {
            return html! {};
        }
        let total: f64 = timings.iter().map(|t| t.seconds.max(0.0)).sum();
        let max = timings
            .iter()
            .map(|t| t.seconds)
            .fold(0.0f64, f64::max)
            .max(1e-9);
        html! {
            h2 { "Timings" }
            table {
                tr { th { "stage" } th { "time" } th {} }
                @for t in timings {
                    @let width = (200.0 * t.seconds.max(0.0) / max).round() as u32;
                    tr {
                        td { (t.stage) }
                        td.num { (fmt_seconds(t.seconds)) }
                        td { div.bar style={ "width:" (width) "px" } {} }
                    }
                }
                tr { th { "total" } th.num { (fmt_seconds(total)) } th {} }
            }
        }
    }
}

/// The metrics table's rows: (metric, value, detail).
fn metric_rows(m: &MetricsSummary) -> Vec<(String, String, String)> {
    let mut rows = Vec::new();
    for (name, c) in [
        ("cross-view error, source renders", &m.source_consistency),
        (
            "cross-view error, guidance (last iteration)",
            &m.guidance_consistency,
        ),
        ("cross-view error, final renders", &m.final_consistency),
    ] {
        if let Some(c) = c {
            rows.push((
                name.to_string(),
                match c.mean_abs_error {
                    Some(e) => format!("{e:.4} · {} dB", fmt_opt(c.psnr, 2)),
                    None => "not measured".to_string(),
                },
                if c.mean_abs_error.is_some() {
                    format!(
                        "mean colour difference (0–1) where views see the same surface, lower is more \
                         consistent, the source renders' the floor; {} pairs, {:.0} % co-visible",
                        c.pairs,
                        100.0 * c.covisible_fraction
                    )
                } else {
                    format!("no pair of views sees the same surface ({} pairs)", c.pairs)
                },
            ));
        }
    }
    for (name, p, meaning) in [
        (
            "preservation outside the mask",
            &m.preservation_outside_mask,
            "source against final renders where the edit may not act: high is kept (≥ 30 dB: barely \
             changed)",
        ),
        (
            "preservation, whole image",
            &m.preservation_whole,
            "source against final renders over the whole image, the edit included: low when the edit \
             changes the whole object, as it should",
        ),
    ] {
        if let Some(p) = p {
            rows.push((
                name.to_string(),
                format!(
                    "PSNR {} dB · SSIM {}",
                    fmt_opt(p.psnr, 2),
                    fmt_opt(p.ssim, 4)
                ),
                format!(
                    "{meaning}; {:.0} % of pixels, {} views",
                    100.0 * p.fraction,
                    p.views
                ),
            ));
        }
    }
    if let Some(f) = m.changed_fraction {
        rows.push((
            "changed where the edit may act".to_string(),
            format!("{:.1} % of pixels", 100.0 * f),
            format!(
                "colour moved by more than {} (0–1 scale); inside the mask when there is one. Near \
                 100 % is expected when the edit recolours the whole object or region; near 0 means it \
                 did nothing",
                crate::eval::metrics::CHANGE_TOLERANCE
            ),
        ));
    }
    if let Some(c) = &m.clip {
        rows.push((
            "CLIP directional similarity".to_string(),
            format!("{:.4}", c.directional),
            format!(
                "image similarity {:.4}, edited↔target text {:.4}",
                c.image_similarity, c.target_text_similarity
            ),
        ));
    }
    for (k, v) in &m.extra {
        rows.push((k.clone(), fmt_opt(Some(*v), 4), String::new()));
    }
    rows
}

/// `value` with its non-integer numbers at the precision they were set with: settings are f32s, whose
/// f64 widening reads 0.699999988079071 for 0.7.
fn tidy_numbers(value: &serde_json::Value) -> serde_json::Value {
    use serde_json::Value;
    match value {
        Value::Number(n) if !(n.is_i64() || n.is_u64()) => n
            .as_f64()
            .and_then(|x| format!("{}", x as f32).parse::<f64>().ok())
            .and_then(serde_json::Number::from_f64)
            .map_or_else(|| value.clone(), Value::Number),
        Value::Array(a) => Value::Array(a.iter().map(tidy_numbers).collect()),
        Value::Object(o) => Value::Object(
            o.iter()
                .map(|(k, v)| (k.clone(), tidy_numbers(v)))
                .collect(),
        ),
        other => other.clone(),
    }
}

/// The report's HTML for output folder `dir` (which is where the referenced files are looked up). All text
/// from the data is escaped by the template.
pub fn render_html(dir: &Path, data: &ReportData, options: &ReportOptions) -> String {
    page_html(dir, data, options, None)
}

/// [`render_html`] with an "Explore in 3D" section holding `viewer` (a `present::viewer` fragment) after
/// the header.
pub fn render_html_with_viewer(
    dir: &Path,
    data: &ReportData,
    options: &ReportOptions,
    viewer: &Markup,
) -> String {
    page_html(dir, data, options, Some(viewer))
}

fn page_html(
    dir: &Path,
    data: &ReportData,
    options: &ReportOptions,
    viewer: Option<&Markup>,
) -> String {
    let page = Page { dir, opts: options };
    let title = if data.title.is_empty() {
        "vcedit run"
    } else {
        &data.title
    };
    super::html_page(
        title,
        CSS,
        html! {
            (page.header(data, title))
            @if let Some(v) = viewer {
                h2 { "Explore in 3D" }
                (v)
            }
            (page.turntable(&data.turntable))
            (page.before_after(&data.views))
            (page.metrics(&data.metrics, &data.runs))
            (page.iterations(&data.iterations))
            (page.attention(&data.attention, &data.masks))
            (page.timings(&data.timings))
            (page.settings(&data.settings))
            p.muted { "Written by vcedit " (env!("CARGO_PKG_VERSION")) "." }
            script { (PreEscaped(BROKEN_IMAGE_CHECK)) }
        },
    )
}

/// Writes `dir/report.html` atomically and returns its path.
pub fn write_report(
    dir: &Path,
    data: &ReportData,
    options: &ReportOptions,
) -> Result<PathBuf, ReportError> {
    write_page(dir, &render_html(dir, data, options))
}

/// Writes `dir/report.html` with the 3D viewer (see [`render_html_with_viewer`]) and returns its path.
pub fn write_report_with_viewer(
    dir: &Path,
    data: &ReportData,
    options: &ReportOptions,
    viewer: &Markup,
) -> Result<PathBuf, ReportError> {
    write_page(dir, &render_html_with_viewer(dir, data, options, viewer))
}

fn write_page(dir: &Path, html: &str) -> Result<PathBuf, ReportError> {
    let path = dir.join(REPORT_FILE);
    files::atomic_write(&path, html.as_bytes()).map_err(|e| ReportError::Write {
        path: path.clone(),
        msg: e.to_string(),
    })?;
    Ok(path)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn escaping_covers_markup_and_quotes() {
        let data = ReportData {
            title: r#"<script>alert("x")</script> & 'y'"#.into(),
            ..Default::default()
        };
        let html = render_html(Path::new("/nonexistent"), &data, &ReportOptions::default());
        // Every attribute is double-quoted, so an apostrophe cannot end one and stays as it is.
        assert!(
            html.contains("<h1>&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; 'y'</h1>")
        );
        assert_eq!(
            html.matches("<script").count(),
            1,
            "only the page's own script"
        );
    }

    #[test]
    fn hrefs_are_relative_and_encoded() {
        let dir = Path::new("/tmp/run");
        assert_eq!(
            href(dir, Path::new("iter_0/guidance/v 1#.png")),
            "iter_0/guidance/v%201%23.png"
        );
        assert_eq!(href(dir, Path::new("/tmp/run/a/b.png")), "a/b.png");
        assert_eq!(href(dir, Path::new("/tmp/other/c.png")), "../other/c.png");
        assert_eq!(
            href(dir, Path::new("/tmp/run/../x/ü.png")),
            "../x/%C3%BC.png"
        );
    }

    #[test]
    fn subsets_are_even_and_bounded() {
        assert_eq!(subset_indices(5, 8), vec![0, 1, 2, 3, 4]);
        assert_eq!(subset_indices(10, 4), vec![0, 3, 6, 9]);
        assert_eq!(subset_indices(10, 1), vec![0]);
        assert_eq!(subset_indices(0, 3), Vec::<usize>::new());
    }

    #[test]
    fn user_text_is_escaped_everywhere() {
        let evil = "<img src=x onerror=alert(1)>\"'&";
        let data = ReportData {
            title: evil.into(),
            source_prompt: evil.into(),
            target_prompt: evil.into(),
            scene: Some(evil.into()),
            notes: vec![evil.into()],
            settings: serde_json::json!({ evil: evil }),
            attention: vec![WordImage {
                word: evil.into(),
                path: PathBuf::from(evil),
            }],
            views: vec![ViewPair {
                name: evil.into(),
                before: PathBuf::from(evil),
                after: PathBuf::from("b.png"),
            }],
            timings: vec![StageTiming {
                stage: evil.into(),
                seconds: 1.0,
            }],
            runs: vec![RunSummary {
                name: evil.into(),
                ..Default::default()
            }],
            metrics: MetricsSummary {
                extra: [(evil.to_string(), 1.0)].into_iter().collect(),
                ..Default::default()
            },
            ..Default::default()
        };
        let html = render_html(Path::new("/nonexistent"), &data, &ReportOptions::default());
        assert!(!html.contains("<img src=x"), "unescaped user text");
        assert!(!html.contains("onerror=alert(1)>\""));
        assert!(html.contains("&lt;img src=x onerror=alert(1)&gt;&quot;'&amp;"));
    }

    #[test]
    fn the_viewer_gets_its_own_section_after_the_header() {
        let data = ReportData {
            title: "t".into(),
            notes: vec!["a note".into()],
            turntable: Some("turntable.gif".into()),
            ..Default::default()
        };
        let viewer = html! { div data-vcedit-viewer {} };
        let dir = Path::new("/nonexistent");
        let html = render_html_with_viewer(dir, &data, &ReportOptions::default(), &viewer);
        let at = |needle: &str| {
            html.find(needle)
                .unwrap_or_else(|| panic!("{needle} missing"))
        };
        assert!(at("a note") < at("Explore in 3D"));
        assert!(at("Explore in 3D") < at("data-vcedit-viewer"));
        assert!(at("data-vcedit-viewer") < at("Turntable"));
        assert!(!render_html(dir, &data, &ReportOptions::default()).contains("Explore in 3D"));
    }

    #[test]
    fn the_report_explains_its_numbers() {
        let preservation = PreservationReport {
            psnr: Some(10.91),
            ssim: Some(0.5),
            pixels: 100,
            fraction: 1.0,
            views: 4,
        };
        let data = ReportData {
            title: "t".into(),
            settings: serde_json::json!({ "cross": 0.699999988079071f64, "steps": 15 }),
            iterations: vec![
                IterationInfo {
                    index: 0,
                    source_prompt: Some("a red sphere".into()),
                    ..Default::default()
                },
                IterationInfo {
                    index: 1,
                    source_prompt: Some("a blue sphere".into()),
                    ..Default::default()
                },
            ],
            metrics: MetricsSummary {
                preservation_whole: Some(preservation),
                changed_fraction: Some(1.0),
                final_consistency: Some(ConsistencySummary {
                    mean_abs_error: None,
                    psnr: None,
                    pairs: 0,
                    covisible_fraction: 0.0,
                    covisible_pixels: 0,
                }),
                ..Default::default()
            },
            ..Default::default()
        };
        let html = render_html(Path::new("/nonexistent"), &data, &ReportOptions::default());
        // A low whole-image PSNR and every pixel changed are what a whole-object edit does: said so.
        assert!(
            html.contains("low when the edit changes the whole object"),
            "{html}"
        );
        assert!(html.contains("Near 100 % is expected"), "{html}");
        // Settings read as they were set.
        assert!(
            html.contains(">0.7<") && !html.contains("0.699999988"),
            "{html}"
        );
        // The second iteration's source prompt is explained, and a metric not measured is said so.
        assert!(
            html.contains("so its source prompt is the target prompt"),
            "{html}"
        );
        assert!(
            !html.contains("– · – dB") && html.contains("no pair of views sees the same surface")
        );
    }

    #[test]
    fn report_data_roundtrips_through_json() {
        let data = ReportData {
            title: "t".into(),
            iterations: vec![IterationInfo {
                index: 0,
                guidance: vec!["iter_0/guidance/000.png".into()],
                guidance_consistency: Some(ConsistencySummary {
                    mean_abs_error: Some(0.1),
                    psnr: Some(20.0),
                    pairs: 4,
                    covisible_fraction: 0.5,
                    covisible_pixels: 10,
                }),
                ..Default::default()
            }],
            ..Default::default()
        };
        let json = serde_json::to_string(&data).unwrap();
        let back: ReportData = serde_json::from_str(&json).unwrap();
        assert_eq!(back, data);
        // Older/partial run.json files without optional sections still load.
        let minimal: ReportData =
            serde_json::from_str(r#"{"title":"x","source_prompt":"a","target_prompt":"b"}"#)
                .unwrap();
        assert!(minimal.views.is_empty());
    }
}
