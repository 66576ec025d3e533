//! The run report: `report.html`, a single self-contained page that opens from disk (no server, no
//! external resources, inline CSS) and links the run's images by relative paths. It needs no JavaScript;
//! one small inline script only reports images that failed to load on the browser console.
//!
//! The editing loop fills a [`ReportData`] (also serialisable into `run.json`) and calls [`write_report`].
//! Paths inside `ReportData` are relative to the output folder the report is written into (absolute
//! paths are accepted and made relative). Files that do not exist when the report is written are shown as
//! "missing" instead of as broken images.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Component, Path, PathBuf};

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

/// Escapes text for HTML element content and quoted attribute values.
pub fn escape_html(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for ch in s.chars() {
        match ch {
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
body{margin:0;padding:24px 32px 48px;font:15px/1.45 system-ui,-apple-system,'Segoe UI',Roboto,sans-serif;color:var(--fg);background:var(--bg)}
h1{font-size:26px;margin:0 0 6px}
h2{font-size:19px;margin:34px 0 10px;padding-bottom:4px;border-bottom:1px solid var(--line)}
h3{font-size:15px;margin:18px 0 6px;color:var(--muted)}
.prompts{font-size:17px;margin:4px 0 14px}
.prompts .arrow{color:var(--muted);padding:0 8px}
.muted{color:var(--muted)}
.notes{background:#fff6e0;border:1px solid #f0d9a0;padding:8px 12px;border-radius:6px;margin:10px 0}
table{border-collapse:collapse;margin:6px 0 12px;background:#fff}
th,td{border:1px solid var(--line);padding:4px 10px;text-align:left;vertical-align:top}
th{background:#f0f2f3;font-weight:600}
td.num{text-align:right;font-variant-numeric:tabular-nums}
.grid{display:flex;flex-wrap:wrap;gap:10px}
figure{margin:0;background:#fff;border:1px solid var(--line);border-radius:6px;padding:6px}
figure img{display:block;height:auto;image-rendering:auto}
figcaption{font-size:12px;color:var(--muted);margin-top:4px;max-width:100%;overflow-wrap:anywhere}
.pair{display:flex;gap:4px}
.missing{display:flex;align-items:center;justify-content:center;background:#eee;color:#a33;font-size:12px;padding:6px;overflow-wrap:anywhere}
.bar{background:var(--accent);height:10px;border-radius:2px}
code{font-size:13px}
";

/// The page's only script, optional for reading it: once everything has loaded, images that failed are
/// reported on the browser console (which the headless-browser test watches) and labelled.
const BROKEN_IMAGE_CHECK: &str = "window.addEventListener('load',function(){\
document.querySelectorAll('img').forEach(function(i){\
if(!i.complete||i.naturalWidth===0){console.error('image failed to load: '+i.getAttribute('src'));\
i.alt='missing: '+i.getAttribute('src');}});});";

struct Writer<'a> {
    dir: &'a Path,
    opts: &'a ReportOptions,
    out: String,
}

impl Writer<'_> {
    fn push(&mut self, s: &str) {
        self.out.push_str(s);
    }

    /// An image thumbnail linking to the full-size file, or a "missing" box.
    fn image(&mut self, path: &Path, alt: &str, width: u32) {
        let resolved = if path.is_absolute() {
            path.to_path_buf()
        } else {
            self.dir.join(path)
        };
        let alt = escape_html(alt);
        if resolved.is_file() {
            let url = href(self.dir, path);
            let _ = write!(
                self.out,
                "<a href=\"{url}\"><img src=\"{url}\" alt=\"{alt}\" width=\"{width}\"></a>"
            );
        } else {
            let _ = write!(
                self.out,
                "<div class=\"missing\" style=\"width:{width}px;height:{h}px\">missing: {p}</div>",
                h = width * 3 / 4,
                p = escape_html(&path.to_string_lossy())
            );
        }
    }

    fn figure(&mut self, path: &Path, caption: &str, width: u32) {
        self.push("<figure>");
        self.image(path, caption, width);
        let _ = write!(
            self.out,
            "<figcaption>{}</figcaption></figure>",
            escape_html(caption)
        );
    }

    fn header(&mut self, d: &ReportData) {
        let title = if d.title.is_empty() {
            "vcedit run"
        } else {
            &d.title
        };
        let _ = write!(
            self.out,
            "<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">\
             <meta name=\"viewport\" content=\"width=device-width, initial-scale=1\">\
             <title>{}</title><style>{CSS}</style></head><body>\n<h1>{}</h1>\n",
            escape_html(title),
            escape_html(title)
        );
        let _ = writeln!(
            self.out,
            "<div class=\"prompts\">“{}”<span class=\"arrow\">→</span>“{}”</div>",
            escape_html(&d.source_prompt),
            escape_html(&d.target_prompt)
        );
        let mut facts = Vec::new();
        if let Some(s) = &d.scene {
            facts.push(format!("scene <code>{}</code>", escape_html(s)));
        }
        if let Some(c) = &d.cameras {
            facts.push(format!("cameras <code>{}</code>", escape_html(c)));
        }
        if let Some(e) = &d.edited_scene {
            facts.push(format!(
                "edited scene <a href=\"{}\"><code>{}</code></a>",
                href(self.dir, e),
                escape_html(&e.to_string_lossy())
            ));
        }
        if !facts.is_empty() {
            let _ = writeln!(self.out, "<p class=\"muted\">{}</p>", facts.join(" · "));
        }
        if !d.notes.is_empty() {
            self.push("<div class=\"notes\">");
            for n in &d.notes {
                let _ = write!(self.out, "<div>{}</div>", escape_html(n));
            }
            self.push("</div>\n");
        }
    }

    fn settings(&mut self, settings: &serde_json::Value) {
        let Some(map) = settings.as_object() else {
            if !settings.is_null() {
                let _ = writeln!(
                    self.out,
                    "<h2>Settings</h2><pre>{}</pre>",
                    escape_html(&settings.to_string())
                );
            }
            return;
        };
        if map.is_empty() {
            return;
        }
        self.push("<h2>Settings</h2><table>\n");
        for (k, v) in map {
            let shown = match v {
                serde_json::Value::String(s) => s.clone(),
                other => other.to_string(),
            };
            let _ = writeln!(
                self.out,
                "<tr><th>{}</th><td><code>{}</code></td></tr>",
                escape_html(k),
                escape_html(&shown)
            );
        }
        self.push("</table>\n");
    }

    fn turntable(&mut self, gif: &Option<PathBuf>) {
        if let Some(g) = gif {
            self.push("<h2>Turntable</h2><div class=\"grid\">");
            let w = self.opts.thumb_px * 2;
            self.figure(g, "edited scene, orbit", w);
            self.push("</div>\n");
        }
    }

    fn before_after(&mut self, views: &[ViewPair]) {
        if views.is_empty() {
            return;
        }
        let shown = subset_indices(views.len(), self.opts.max_views);
        let _ = write!(
            self.out,
            "<h2>Before / after</h2><p class=\"muted\">{} of {} views; click an image for full size.</p><div class=\"grid\">",
            shown.len(),
            views.len()
        );
        for &i in &shown {
            let v = &views[i];
            self.push("<figure><div class=\"pair\">");
            let w = self.opts.thumb_px;
            self.image(&v.before, &format!("{} before", v.name), w);
            self.image(&v.after, &format!("{} after", v.name), w);
            let _ = write!(
                self.out,
                "</div><figcaption>{} — source | edited</figcaption></figure>",
                escape_html(&v.name)
            );
        }
        self.push("</div>\n");
    }

    fn iterations(&mut self, iterations: &[IterationInfo]) {
        if iterations.is_empty() {
            return;
        }
        self.push("<h2>Guidance per iteration</h2>\n");
        for it in iterations {
            let mut head = format!("Iteration {}", it.index + 1);
            if let Some(p) = &it.source_prompt {
                head.push_str(&format!(" · source prompt “{}”", escape_html(p)));
            }
            if let Some(c) = &it.guidance_consistency {
                head.push_str(&format!(
                    " · cross-view error {} ({} dB)",
                    fmt_opt(c.mean_abs_error, 4),
                    fmt_opt(c.psnr, 2)
                ));
            }
            if let Some(s) = it.seconds {
                head.push_str(&format!(" · {}", fmt_seconds(s)));
            }
            let _ = write!(self.out, "<h3>{head}</h3>");
            for (label, list) in [
                ("guidance", &it.guidance),
                ("render after fit", &it.renders),
            ] {
                if list.is_empty() {
                    continue;
                }
                self.push("<div class=\"grid\">");
                let w = self.opts.thumb_px * 3 / 4;
                for i in subset_indices(list.len(), self.opts.max_views) {
                    self.figure(&list[i], &format!("view {i} {label}"), w);
                }
                self.push("</div>\n");
            }
        }
    }

    fn attention(&mut self, words: &[WordImage], masks: &[PathBuf]) {
        if words.is_empty() && masks.is_empty() {
            return;
        }
        self.push("<h2>Attention and mask</h2>");
        let w = self.opts.thumb_px * 3 / 4;
        if !words.is_empty() {
            self.push("<div class=\"grid\">");
            for wi in words {
                self.figure(&wi.path, &format!("“{}”", wi.word), w);
            }
            self.push("</div>\n");
        }
        if !masks.is_empty() {
            self.push("<h3>Editable mask</h3><div class=\"grid\">");
            for i in subset_indices(masks.len(), self.opts.max_views) {
                self.figure(&masks[i], &format!("mask, view {i}"), w);
            }
            self.push("</div>\n");
        }
    }

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
                    format!(
                        "{} · {} dB",
                        fmt_opt(c.mean_abs_error, 4),
                        fmt_opt(c.psnr, 2)
                    ),
                    format!(
                        "{} pairs, {:.0} % co-visible",
                        c.pairs,
                        100.0 * c.covisible_fraction
                    ),
                ));
            }
        }
        for (name, p) in [
            (
                "preservation outside the mask",
                &m.preservation_outside_mask,
            ),
            ("preservation, whole image", &m.preservation_whole),
        ] {
            if let Some(p) = p {
                rows.push((
                    name.to_string(),
                    format!(
                        "PSNR {} dB · SSIM {}",
                        fmt_opt(p.psnr, 2),
                        fmt_opt(p.ssim, 4)
                    ),
                    format!("{:.0} % of pixels, {} views", 100.0 * p.fraction, p.views),
                ));
            }
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
            rows.push((escape_html(k), fmt_opt(Some(*v), 4), String::new()));
        }
        rows
    }

    fn metrics(&mut self, m: &MetricsSummary, runs: &[RunSummary]) {
        let rows = Self::metric_rows(m);
        if !rows.is_empty() {
            self.push(
                "<h2>Metrics</h2><table><tr><th>metric</th><th>value</th><th>detail</th></tr>\n",
            );
            for (name, value, detail) in rows {
                let _ = writeln!(
                    self.out,
                    "<tr><td>{name}</td><td class=\"num\">{value}</td><td class=\"muted\">{detail}</td></tr>"
                );
            }
            self.push("</table><p class=\"muted\">Cross-view error: mean absolute colour difference (0–1 scale) between each view and its nearest cameras, warped with the scene's rendered depth, over co-visible pixels; lower is more consistent.</p>\n");
        }
        if runs.is_empty() {
            return;
        }
        self.push(
            "<h2>Comparison</h2><table><tr><th>run</th><th>guidance error</th><th>final error</th>\
             <th>final PSNR</th><th>PSNR outside</th><th>SSIM outside</th><th>CLIP dir.</th></tr>\n",
        );
        for r in runs {
            let m = &r.metrics;
            let name = match &r.report {
                Some(p) => format!(
                    "<a href=\"{}\">{}</a>",
                    href(self.dir, p),
                    escape_html(&r.name)
                ),
                None => escape_html(&r.name),
            };
            let err = |c: &Option<ConsistencySummary>| {
                fmt_opt(c.as_ref().and_then(|c| c.mean_abs_error), 4)
            };
            let pres = m
                .preservation_outside_mask
                .as_ref()
                .or(m.preservation_whole.as_ref());
            let _ = writeln!(
                self.out,
                "<tr><td>{name}</td><td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td>\
                 <td class=\"num\">{}</td><td class=\"num\">{}</td><td class=\"num\">{}</td></tr>",
                err(&m.guidance_consistency),
                err(&m.final_consistency),
                fmt_opt(m.final_consistency.as_ref().and_then(|c| c.psnr), 2),
                fmt_opt(pres.and_then(|p| p.psnr), 2),
                fmt_opt(pres.and_then(|p| p.ssim), 4),
                fmt_opt(m.clip.as_ref().map(|c| c.directional), 4),
            );
        }
        self.push("</table>\n");
    }

    fn timings(&mut self, timings: &[StageTiming]) {
        if timings.is_empty() {
            return;
        }
        let total: f64 = timings.iter().map(|t| t.seconds.max(0.0)).sum();
        let max = timings
            .iter()
            .map(|t| t.seconds)
            .fold(0.0f64, f64::max)
            .max(1e-9);
        self.push("<h2>Timings</h2><table><tr><th>stage</th><th>time</th><th></th></tr>\n");
        for t in timings {
            let width = (200.0 * t.seconds.max(0.0) / max).round() as u32;
            let _ = writeln!(
                self.out,
                "<tr><td>{}</td><td class=\"num\">{}</td><td><div class=\"bar\" style=\"width:{width}px\"></div></td></tr>",
                escape_html(&t.stage),
                fmt_seconds(t.seconds)
            );
        }
        let _ = writeln!(
            self.out,
            "<tr><th>total</th><th class=\"num\">{}</th><th></th></tr></table>",
            fmt_seconds(total)
        );
    }
}

/// The report's HTML for output folder `dir` (which is where the referenced files are looked up).
pub fn render_html(dir: &Path, data: &ReportData, options: &ReportOptions) -> String {
    let mut w = Writer {
        dir,
        opts: options,
        out: String::new(),
    };
    w.header(data);
    w.turntable(&data.turntable);
    w.before_after(&data.views);
    w.metrics(&data.metrics, &data.runs);
    w.iterations(&data.iterations);
    w.attention(&data.attention, &data.masks);
    w.timings(&data.timings);
    w.settings(&data.settings);
    w.push(&format!(
        "<p class=\"muted\">Written by vcedit {}.</p>\n<script>{BROKEN_IMAGE_CHECK}</script>\n</body></html>\n",
        env!("CARGO_PKG_VERSION")
    ));
    w.out
}

/// Writes `dir/report.html` atomically and returns its path.
pub fn write_report(
    dir: &Path,
    data: &ReportData,
    options: &ReportOptions,
) -> Result<PathBuf, ReportError> {
    let path = dir.join(REPORT_FILE);
    let html = render_html(dir, data, options);
    splat::atomic_write(&path, html.as_bytes()).map_err(|e| ReportError::Write {
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
        assert_eq!(
            escape_html(r#"<script>alert("x")</script> & 'y'"#),
            "&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; &#39;y&#39;"
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
        assert!(html.contains("&lt;img src=x onerror=alert(1)&gt;&quot;&#39;&amp;"));
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
