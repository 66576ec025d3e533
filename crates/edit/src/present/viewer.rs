//! The interactive 3D viewer: an HTML fragment (canvas, controls, the scenes embedded as base64, and the
//! WebGL2 script `viewer.js`) that the run report includes, and a standalone page for `vcedit view`.
//!
//! Embedded data: each scene becomes 32-byte records in antimatter15's `.splat` layout (see
//! [`pack_record`]), base64-encoded inside a `<script type="application/octet-stream">`: 42⅔ characters per
//! Gaussian. Scenes larger than the cap keep their most visible Gaussians (opacity × the area of the
//! largest cross-section), chosen deterministically. With the default cap of [`DEFAULT_CAP`] a page holds
//! at most 2 × 250 000 × 42⅔ B ≈ 21.3 MB of scene data; two scenes of 125 000 Gaussians take 10.7 MB.
//!
//! Colours: the DC colour in the record, and for scenes of SH degree 1 to 3 the higher coefficients, one
//! byte each ([`pack_sh`]: 9, 24 or 45 more bytes per Gaussian, after all the records; `data-sh-degree` on
//! the script says how many bands), so shading changes with the viewing direction as in the renderer.
//! Bands whose coefficients all quantise to zero are left out (see [`embedded_sh_degree`]), and the top
//! bands are dropped where the page's scene data would pass [`SH_PAGE_BUDGET_BYTES`] (two scenes of
//! 250 000 Gaussians keep degree 1, 27.3 MB; two of 125 000 keep degree 3, 25.7 MB).

use std::path::Path;

use maud::{html, Markup, PreEscaped};
use serde::Serialize;
use splat::cameras::orbit::{focus_point, look_at};
use splat::cameras::{orbit_cameras, robust_bounds, OrbitSettings};
use splat::{Camera, GaussianScene};

/// The viewer's script (WebGL2 renderer, controls); readable on its own in `present/viewer.js`.
const VIEWER_JS: &str = include_str!("viewer.js");

/// Bytes per Gaussian in the embedded records.
pub const RECORD_BYTES: usize = splat::formats::dot_splat::RECORD_BYTES;
/// The highest SH degree the viewer evaluates (that of the renderer and of every scene format).
pub const MAX_SH_DEGREE: u32 = 3;
/// Default number of Gaussians embedded per scene.
pub const DEFAULT_CAP: usize = 250_000;
/// Most bytes (base64, all scenes together) a page's SH bands may bring its scene data to: degree 3
/// nearly doubles a Gaussian's bytes, and a page must still open quickly in a browser tab. Records
/// alone are never dropped (`--cap` limits them).
pub const SH_PAGE_BUDGET_BYTES: usize = 28_000_000;
/// Base64 characters per embedded byte.
const BASE64_PER_BYTE: f64 = 4.0 / 3.0;
/// The zeroth-order SH basis constant: colour = 0.5 + C0 · DC coefficient.
#[cfg(test)]
const SH_C0: f32 = 0.282_094_8;
/// Gaussians fainter than this can never pass the renderer's alpha test.
const MIN_OPACITY: f32 = 1.0 / 255.0;

#[derive(Debug, thiserror::Error)]
pub enum ViewerError {
    #[error("{}: cannot write the viewer page: {msg}", .path.display())]
    Write {
        path: std::path::PathBuf,
        msg: String,
    },
}

/// One Gaussian as the viewer receives it, decoded from its record.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Record {
    pub position: [f32; 3],
    /// Per-axis standard deviations (linear, not log).
    pub scale: [f32; 3],
    /// DC colour in [0, 1] (clamped), quantised to 1/255.
    pub color: [f32; 3],
    /// Opacity in [0, 1], quantised to 1/255.
    pub opacity: f32,
    /// Unit quaternion (w, x, y, z) with w ≥ 0; each component quantised to 1/128.
    pub rotation: [f32; 4],
}

/// Packs Gaussian `i` of `scene` into the 32-byte `.splat` record (little-endian):
/// position f32×3 | scale f32×3 (exp of the log-scales) | colour RGBA u8×4 (0.5 + C0·DC clamped to
/// [0, 1], A = sigmoid of the opacity logit) | rotation u8×4 (the normalised quaternion w, x, y, z with
/// w ≥ 0, each component c stored as round(128 c + 128) clamped to 0..=255).
///
/// This is exactly a record of antimatter15's `.splat` files, as `splat::formats::dot_splat` writes them.
pub fn pack_record(scene: &GaussianScene, i: usize) -> [u8; RECORD_BYTES] {
    splat::formats::dot_splat::encode_record(scene, i)
}

/// Bytes per Gaussian of the SH coefficients above the DC term up to `degree` (RGB each, one byte per
/// value): 0, 9, 24 or 45 for degrees 0 to 3.
pub fn sh_bytes(degree: u32) -> usize {
    3 * (splat::scene::sh_coeffs(degree.min(MAX_SH_DEGREE)) - 1)
}

/// One SH coefficient as a byte: round(128 v + 128) clamped to 0..=255 (as `.spz` stores SH), so steps of
/// 1/128 over [-1, 1).
fn quantise_sh(v: f32) -> u8 {
    (v * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8
}

/// The SH coefficients of Gaussian `i` above the DC term, up to `degree` (coefficient-major, channel inner,
/// as `GaussianScene::sh`), each quantised to a byte by round(128 v + 128) clamped to 0..=255: steps of
/// 1/128 over [-1, 1). Bands the scene does not have are zero (128). [`sh_bytes`]`(degree)` long.
pub fn pack_sh(scene: &GaussianScene, i: usize, degree: u32) -> Vec<u8> {
    let wanted = sh_bytes(degree);
    let have = sh_bytes(scene.sh_degree).min(wanted);
    let row = &scene.sh[i * 3 * scene.sh_coeffs() + 3..][..have];
    let mut out: Vec<u8> = row.iter().map(|&v| quantise_sh(v)).collect();
    out.resize(wanted, 128);
    out
}

/// The SH degree to embed for the Gaussians `kept` of `scene`: the scene's degree (at most 3), lowered
/// past every top band whose coefficients all quantise to zero, so a scene stored with SH it never used
/// costs no more than a scene of degree 0.
pub fn embedded_sh_degree(scene: &GaussianScene, kept: &[usize]) -> u32 {
    let coeffs = scene.sh_coeffs();
    (1..=scene.sh_degree.min(MAX_SH_DEGREE))
        .rev()
        .find(|&degree| {
            // Values of the band `degree` within a Gaussian's row: after the lower bands.
            let band = 3 * splat::scene::sh_coeffs(degree - 1)..3 * splat::scene::sh_coeffs(degree);
            kept.iter().any(|&i| {
                scene.sh[i * 3 * coeffs..][band.clone()]
                    .iter()
                    .any(|&v| quantise_sh(v) != 128)
            })
        })
        .unwrap_or(0)
}

/// Decodes a record written by [`pack_record`].
pub fn unpack_record(bytes: &[u8; RECORD_BYTES]) -> Record {
    let f = |k: usize| f32::from_le_bytes(bytes[4 * k..4 * k + 4].try_into().expect("4 bytes"));
    let q: [f32; 4] = std::array::from_fn(|k| (f32::from(bytes[28 + k]) - 128.0) / 128.0);
    let norm = q
        .iter()
        .map(|v| v * v)
        .sum::<f32>()
        .sqrt()
        .max(f32::MIN_POSITIVE);
    Record {
        position: [f(0), f(1), f(2)],
        scale: [f(3), f(4), f(5)],
        color: std::array::from_fn(|c| f32::from(bytes[24 + c]) / 255.0),
        opacity: f32::from(bytes[27]) / 255.0,
        rotation: q.map(|v| v / norm),
    }
}

/// The Gaussians to embed, in scene order: every one that can be seen (finite, opacity ≥ 1/255), or when
/// there are more than `cap`, the `cap` most visible by opacity × the product of the two largest scales
/// (ties to the lower index, so the choice is deterministic).
pub fn visible_subset(scene: &GaussianScene, cap: usize) -> Vec<usize> {
    let score = |i: usize| -> Option<f64> {
        let finite = scene.means[3 * i..3 * i + 3]
            .iter()
            .chain(&scene.log_scales[3 * i..3 * i + 3])
            .chain(&scene.quats[4 * i..4 * i + 4])
            .all(|v| v.is_finite());
        let opacity = scene.opacity(i);
        // A NaN opacity fails the comparison too.
        let visible = finite && opacity >= MIN_OPACITY;
        if !visible {
            return None;
        }
        let mut ls = [0, 1, 2].map(|a| f64::from(scene.log_scales[3 * i + a]));
        ls.sort_by(f64::total_cmp);
        Some(f64::from(opacity) * (ls[1] + ls[2]).exp())
    };
    let mut ranked: Vec<(f64, usize)> = (0..scene.len())
        .filter_map(|i| score(i).map(|s| (s, i)))
        .collect();
    if ranked.len() > cap {
        let by_visibility =
            |a: &(f64, usize), b: &(f64, usize)| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1));
        if cap > 0 {
            ranked.select_nth_unstable_by(cap - 1, by_visibility);
        }
        ranked.truncate(cap);
    }
    let mut kept: Vec<usize> = ranked.into_iter().map(|(_, i)| i).collect();
    kept.sort_unstable();
    kept
}

/// Standard base64 (RFC 4648, with padding).
fn base64(bytes: &[u8]) -> String {
    const ALPHABET: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let b = [
            chunk[0],
            *chunk.get(1).unwrap_or(&0),
            *chunk.get(2).unwrap_or(&0),
        ];
        let n = u32::from(b[0]) << 16 | u32::from(b[1]) << 8 | u32::from(b[2]);
        for k in 0..4 {
            if k <= chunk.len() {
                out.push(ALPHABET[(n >> (18 - 6 * k) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// Where the viewer starts and what it turns around.
#[derive(Clone, Debug, PartialEq)]
pub struct InitialView {
    /// The starting camera; its aspect ratio is the canvas's, its intrinsics are scaled to the canvas.
    pub camera: Camera,
    /// The point orbiting turns around.
    pub pivot: [f64; 3],
    /// The world's up direction (horizontal drags turn about it).
    pub up: [f64; 3],
}

impl InitialView {
    /// The first of `cameras`, turning around `pivot` when given, else the point the cameras look at
    /// (when it is in front of the first camera), else the scene's per-axis median. Without cameras: an
    /// orbit camera looking at the scene's bounds (see [`InitialView::around`]).
    pub fn from_cameras(
        cameras: &[Camera],
        scene: &GaussianScene,
        pivot: Option<[f64; 3]>,
    ) -> InitialView {
        let Some(first) = cameras.first() else {
            return Self::around(scene);
        };
        let in_front = |p: &[f64; 3]| first.world_to_camera(*p)[2] > 0.0;
        let pivot = pivot
            .or_else(|| focus_point(cameras).filter(in_front))
            .or_else(|| median(scene).filter(in_front))
            .unwrap_or_else(|| {
                // A point straight ahead, as far as the cameras are apart (or 1).
                let spread = cameras
                    .iter()
                    .map(|c| distance(c.center(), first.center()))
                    .fold(0.0, f64::max);
                let d = if spread > 0.0 { spread } else { 1.0 };
                std::array::from_fn(|a| first.center()[a] + d * first.rotation[2][a])
            });
        // Image y points down, so the world's up is minus the cameras' mean y axis.
        let up_sum = cameras.iter().fold([0.0; 3], |acc, c| {
            std::array::from_fn(|a| acc[a] - c.rotation[1][a])
        });
        let up = normalized(up_sum).unwrap_or(first.rotation[1].map(|v| -v));
        InitialView {
            camera: first.clone(),
            pivot,
            up,
        }
    }

    /// A camera looking at the scene from 20° above, on the orbit `vcedit render` uses for bare scenes,
    /// turning around the centre of the scene's bounds (1st–99th percentile).
    pub fn around(scene: &GaussianScene) -> InitialView {
        let (lo, hi) = robust_bounds(scene, 0.01).unwrap_or(([-1.0; 3], [1.0; 3]));
        let camera = orbit_cameras(lo, hi, 1, 800, 600).pop().unwrap_or_else(|| {
            let eye = [0.0, 0.0, -3.0];
            look_at(
                "view".into(),
                eye,
                [0.0; 3],
                [0.0, -1.0, 0.0],
                800,
                600,
                600.0,
            )
        });
        let pivot = std::array::from_fn(|a| 0.5 * (f64::from(lo[a]) + f64::from(hi[a])));
        // The orbit's world axis, not the camera's up: the camera looks down 20°, so turning about its
        // own up vector would tilt the horizon at every horizontal drag.
        let up = normalized(OrbitSettings::default().up.resolve(lo, hi))
            .unwrap_or_else(|| camera.rotation[1].map(|v| -v));
        InitialView { camera, pivot, up }
    }
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    (0..3).map(|k| (a[k] - b[k]).powi(2)).sum::<f64>().sqrt()
}

fn normalized(v: [f64; 3]) -> Option<[f64; 3]> {
    let n = v.iter().map(|x| x * x).sum::<f64>().sqrt();
    (n > 1e-12 && n.is_finite()).then(|| v.map(|x| x / n))
}

/// Per-axis median of the means (robust to floaters); `None` for an empty scene.
fn median(scene: &GaussianScene) -> Option<[f64; 3]> {
    robust_bounds(scene, 0.5).map(|(lo, _)| lo.map(f64::from))
}

/// A scene to show, with the name the controls give it.
pub struct ViewerScene<'a> {
    pub label: &'a str,
    pub scene: &'a GaussianScene,
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ViewerOptions {
    /// Most Gaussians embedded per scene.
    pub cap: usize,
    /// Colour behind the Gaussians, RGB in [0, 1].
    pub background: [f32; 3],
}

impl Default for ViewerOptions {
    fn default() -> Self {
        Self {
            cap: DEFAULT_CAP,
            background: [0.0; 3],
        }
    }
}

/// What the script reads from `script.vcv-config` (names and labels stay in the markup).
#[derive(Serialize)]
struct Config {
    camera: CameraConfig,
    pivot: [f64; 3],
    up: [f64; 3],
    background: [f32; 3],
}

#[derive(Serialize)]
struct CameraConfig {
    width: u32,
    height: u32,
    fx: f64,
    fy: f64,
    cx: f64,
    cy: f64,
    rotation: [[f64; 3]; 3],
    translation: [f64; 3],
}

/// JSON that can sit inside a `<script>` element: `<`, `>` and `&` as JSON escapes.
fn script_json<T: Serialize>(value: &T) -> String {
    serde_json::to_string(value)
        .expect("plain data serialises")
        .replace('<', "\\u003c")
        .replace('>', "\\u003e")
        .replace('&', "\\u0026")
}

/// "12 345"-style thousands grouping for the page's text.
fn grouped(n: usize) -> String {
    let digits = n.to_string();
    let mut out = String::new();
    for (k, ch) in digits.chars().enumerate() {
        if k > 0 && (digits.len() - k).is_multiple_of(3) {
            out.push('\u{202f}');
        }
        out.push(ch);
    }
    out
}

const CSS: &str = "
.vcv{margin:8px 0 16px}
.vcv-stage{position:relative;width:100%;background:#000;border-radius:6px;overflow:hidden;line-height:0}
.vcv-stage canvas{display:block;width:100%;cursor:grab;touch-action:none;outline:none}
.vcv-stage canvas:active{cursor:grabbing}
.vcv-stage canvas:focus-visible{box-shadow:inset 0 0 0 2px #2a6f97}
.vcv:fullscreen{margin:0;background:#000}
.vcv:fullscreen .vcv-stage{height:100%;border-radius:0}
.vcv:fullscreen .vcv-stage canvas{height:100%;max-height:none!important;aspect-ratio:auto!important}
.vcv:fullscreen .vcv-controls{position:absolute;left:8px;bottom:8px;margin:0;padding:4px 6px;border-radius:6px;background:rgba(255,255,255,.85)}
.vcv:fullscreen .vcv-note{display:none}
.vcv-divider{position:absolute;top:0;bottom:0;width:2px;margin-left:-1px;background:rgba(255,255,255,.85);pointer-events:none}
.vcv-tag{position:absolute;top:8px;padding:2px 8px;border-radius:4px;background:rgba(0,0,0,.55);color:#fff;font:13px/1.4 system-ui,sans-serif;pointer-events:none}
.vcv-tag-0{left:8px}.vcv-tag-1{right:8px}
.vcv[data-mode=before] .vcv-tag-1,.vcv[data-mode=after] .vcv-tag-0,.vcv[data-mode=before] .vcv-divider,.vcv[data-mode=after] .vcv-divider{display:none}
.vcv-message{position:absolute;left:0;right:0;top:45%;text-align:center;color:#fff;font:15px/1.4 system-ui,sans-serif}
.vcv-controls{display:flex;flex-wrap:wrap;align-items:center;gap:6px;margin:8px 0 4px;font:14px system-ui,sans-serif}
.vcv-controls button{font:inherit;padding:3px 12px;border:1px solid #b8c0c5;border-radius:4px;background:#fff;cursor:pointer}
.vcv[data-mode=before] button[data-mode=before],.vcv[data-mode=after] button[data-mode=after],.vcv[data-mode=split] button[data-mode=split]{background:#2a6f97;border-color:#2a6f97;color:#fff}
.vcv-controls input[type=range]{flex:1;min-width:120px}
.vcv-note{font:12px/1.45 system-ui,sans-serif;color:#5f6b73;margin:2px 0}
";

/// The viewer as an HTML fragment: styles, canvas, controls, embedded scenes (one or two; the first is
/// shown left of the divider, the second right of it) and the script. Labels are escaped by the template.
pub fn viewer_html(
    scenes: &[ViewerScene<'_>],
    view: &InitialView,
    options: &ViewerOptions,
) -> Markup {
    build(scenes, view, options).0
}

/// The fragment and what it embeds of each scene.
fn build(
    scenes: &[ViewerScene<'_>],
    view: &InitialView,
    options: &ViewerOptions,
) -> (Markup, Vec<Embedded>) {
    let cam = &view.camera;
    let config = Config {
        camera: CameraConfig {
            width: cam.width.max(1),
            height: cam.height.max(1),
            fx: cam.fx,
            fy: cam.fy,
            cx: cam.cx,
            cy: cam.cy,
            rotation: cam.rotation,
            translation: cam.translation,
        },
        pivot: view.pivot,
        up: view.up,
        background: options.background,
    };
    let kept: Vec<Vec<usize>> = scenes
        .iter()
        .map(|s| visible_subset(s.scene, options.cap))
        .collect();
    let mut embedded: Vec<Embedded> = scenes
        .iter()
        .zip(&kept)
        .map(|(s, kept)| Embedded {
            count: kept.len(),
            sh_degree: embedded_sh_degree(s.scene, kept),
        })
        .collect();
    fit_sh_to_budget(&mut embedded, SH_PAGE_BUDGET_BYTES);
    let packed: Vec<String> = scenes
        .iter()
        .zip(&kept)
        .zip(&embedded)
        .map(|((s, kept), e)| {
            let mut bytes: Vec<u8> = kept.iter().flat_map(|&i| pack_record(s.scene, i)).collect();
            bytes.extend(kept.iter().flat_map(|&i| pack_sh(s.scene, i, e.sh_degree)));
            base64(&bytes)
        })
        .collect();
    let two = scenes.len() > 1;
    let (w, h) = (cam.width.max(1), cam.height.max(1));
    // As wide as the page, in the first camera's aspect ratio but no taller than 78 % of the window (the
    // script fits the camera into whatever shape the canvas gets).
    let canvas_shape = format!("aspect-ratio:{w}/{h};max-height:78vh");
    let mb_125k_pair = 2.0 * 125_000.0 * (RECORD_BYTES as f64 * BASE64_PER_BYTE) / 1e6;
    let mb_125k_pair_sh3 =
        2.0 * 125_000.0 * ((RECORD_BYTES + sh_bytes(3)) as f64 * BASE64_PER_BYTE) / 1e6;
    let markup = html! {
        style { (PreEscaped(CSS)) }
        div.vcv data-vcedit-viewer data-mode="split" {
            script.vcv-config type="application/json" { (PreEscaped(script_json(&config))) }
            @for ((s, e), data) in scenes.iter().zip(&embedded).zip(&packed) {
                script.vcv-scene type="application/octet-stream" data-label=(s.label)
                    data-sh-degree=[(e.sh_degree > 0).then_some(e.sh_degree)] {
                    (PreEscaped(data))
                }
            }
            div.vcv-stage {
                canvas style=(canvas_shape) tabindex="0"
                    aria-label="3D view: drag to turn, wheel to zoom, W A S D Q E and arrow keys to fly" {}
                @if two {
                    div.vcv-divider style="left:50%" {}
                }
                @for (k, s) in scenes.iter().enumerate().take(2) {
                    span class={ "vcv-tag vcv-tag-" (k) } { (s.label) }
                }
                div.vcv-message {}
            }
            div.vcv-controls {
                @if two {
                    button type="button" data-mode="before" { (scenes[0].label) }
                    button type="button" data-mode="split" { "split" }
                    button type="button" data-mode="after" { (scenes[1].label) }
                    input.vcv-split type="range" min="0" max="100" value="50" aria-label="divider position";
                }
                button type="button" data-action="reset" { "reset view" }
                // Shown by the script where the page may go full screen.
                button type="button" data-action="fullscreen" hidden { "full screen" }
            }
            p.vcv-note {
                "Mouse: drag to turn around the scene, shift- or right-drag to pan, wheel to zoom, double-click \
                 to reset. Keys (click the view first): W/S forward/back, A/D left/right, E/Q up/down (as in \
                 SuperSplat), arrow keys to turn, Shift to move faster. WebGL2 splatting of the embedded \
                 Gaussians with their view-dependent SH colours (up to degree 3)."
            }
            p.vcv-note {
                "Embedded: "
                @for (k, (s, e)) in scenes.iter().zip(&embedded).enumerate() {
                    @if k > 0 { "; " }
                    (s.label) " " (grouped(e.count)) " of " (grouped(s.scene.len())) " Gaussians"
                    @if e.sh_degree > 0 { " with SH degree " (e.sh_degree) }
                }
                " (at most " (grouped(options.cap)) " per scene, the most visible by opacity × area). "
                (RECORD_BYTES) " bytes per Gaussian, " (format!("{:.1}", RECORD_BYTES as f64 * BASE64_PER_BYTE))
                " in the page as base64, and " (sh_bytes(1)) ", " (sh_bytes(2)) " or " (sh_bytes(3))
                " more with SH of degree 1, 2 or 3: two scenes of 125" "\u{202f}" "000 Gaussians take "
                (format!("{mb_125k_pair:.1}")) " MB, " (format!("{mb_125k_pair_sh3:.1}")) " MB at degree 3."
            }
        }
        script { (PreEscaped(VIEWER_JS)) }
    };
    (markup, embedded)
}

/// Drops the top SH band of every scene until the scenes' page bytes fit `budget` or only records are
/// left (records are never dropped: the cap limits them).
fn fit_sh_to_budget(embedded: &mut [Embedded], budget: usize) {
    while embedded.iter().map(Embedded::page_bytes).sum::<usize>() > budget {
        let Some(top) = embedded
            .iter()
            .map(|e| e.sh_degree)
            .max()
            .filter(|&d| d > 0)
        else {
            break;
        };
        for e in embedded.iter_mut() {
            e.sh_degree = e.sh_degree.min(top - 1);
        }
    }
}

/// What a page embeds of one scene.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Embedded {
    /// Gaussians embedded.
    pub count: usize,
    /// SH bands embedded after the records (0 to 3).
    pub sh_degree: u32,
}

impl Embedded {
    /// The scene's data in the page: records and SH bytes, as base64.
    pub fn page_bytes(&self) -> usize {
        ((self.count * (RECORD_BYTES + sh_bytes(self.sh_degree))) as f64 * BASE64_PER_BYTE).ceil()
            as usize
    }
}

/// A standalone page holding only the viewer.
pub fn viewer_page(
    title: &str,
    scenes: &[ViewerScene<'_>],
    view: &InitialView,
    options: &ViewerOptions,
) -> String {
    page(title, build(scenes, view, options).0)
}

fn page(title: &str, viewer: Markup) -> String {
    let css = "body{margin:0;padding:20px 28px;font:15px/1.45 system-ui,sans-serif;color:#1d2327;background:#fbfbfa}h1{font-size:20px;margin:0 0 10px}";
    super::html_page(
        title,
        css,
        html! {
            h1 { (title) }
            (viewer)
        },
    )
}

/// Writes [`viewer_page`] to `path` atomically; returns what it embeds of each scene.
pub fn write_viewer_page(
    path: &Path,
    title: &str,
    scenes: &[ViewerScene<'_>],
    view: &InitialView,
    options: &ViewerOptions,
) -> Result<Vec<Embedded>, ViewerError> {
    let (viewer, embedded) = build(scenes, view, options);
    files::atomic_write(path, page(title, viewer).as_bytes()).map_err(|e| ViewerError::Write {
        path: path.to_path_buf(),
        msg: e.to_string(),
    })?;
    Ok(embedded)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Gaussians with varied parameters, including an unnormalised and a negative-w quaternion and a
    /// colour beyond [0, 1].
    fn varied(n: usize, sh_degree: u32) -> GaussianScene {
        let k = splat::scene::sh_coeffs(sh_degree);
        let mut s = GaussianScene::new(sh_degree);
        for i in 0..n {
            let t = i as f32;
            s.means
                .extend([t * 0.5 - 3.0, (t * 1.7).sin(), -(t * 0.3).cos() * 2.0]);
            s.log_scales
                .extend([-3.0 + 0.1 * t, -2.0, -4.0 + (t * 0.7).sin()]);
            s.quats
                .extend([(t * 0.9).cos() * 2.0, 0.3, -(t * 1.3).sin(), 0.7 - 0.1 * t]);
            s.opacity_logits.push((t * 2.1).sin() * 4.0);
            for j in 0..k {
                let base = if j == 0 { 1.0 } else { 0.1 };
                s.sh.extend([base * (t * 0.4).sin() * 2.5, base * 0.1, -base * 0.2 * t]);
            }
        }
        s
    }

    /// The embedded SH data of a one-scene page: its `data-sh-degree` (0 when absent) and the base64.
    fn embedded(scene: &GaussianScene) -> (u32, String, usize) {
        let view = InitialView::around(scene);
        let (html, kept) = build(
            &[ViewerScene { label: "s", scene }],
            &view,
            &ViewerOptions::default(),
        );
        let html = html.into_string();
        let tag = html.split("data-label=\"s\"").nth(1).unwrap();
        let degree = tag
            .strip_prefix(" data-sh-degree=\"")
            .map_or(0, |rest| rest[..rest.find('"').unwrap()].parse().unwrap());
        let data = &tag[tag.find('>').unwrap() + 1..tag.find("</script>").unwrap()];
        (degree, data.trim().to_string(), kept[0].count)
    }

    #[test]
    fn sh_coefficients_of_every_degree_follow_the_records() {
        for degree in 0..=3 {
            let shaded = varied(5, degree);
            let k = shaded.sh_coeffs();
            assert_eq!(sh_bytes(degree), 3 * (k - 1));
            for i in 0..5 {
                let packed = pack_sh(&shaded, i, degree);
                assert_eq!(packed.len(), sh_bytes(degree));
                for (j, &b) in packed.iter().enumerate() {
                    let want = shaded.sh[i * 3 * k + 3 + j].clamp(-1.0, 127.0 / 128.0);
                    let got = (f32::from(b) - 128.0) / 128.0;
                    assert!(
                        (got - want).abs() <= 0.5 / 128.0 + 1e-6,
                        "degree {degree}, {i}/{j}: {got} vs {want}"
                    );
                }
                // Asking for more bands than the scene has pads with zeros.
                let padded = pack_sh(&shaded, i, 3);
                assert_eq!(&padded[..packed.len()], &packed[..]);
                assert!(padded[packed.len()..].iter().all(|&b| b == 128));
            }
            // The page: records, then the coefficients, and `data-sh-degree` says how many bands.
            let (embedded_degree, data, kept) = embedded(&shaded);
            assert_eq!(embedded_degree, degree);
            let bytes = RECORD_BYTES + sh_bytes(degree);
            assert_eq!(
                data.len(),
                (kept * bytes).div_ceil(3) * 4,
                "degree {degree}"
            );
        }
    }

    #[test]
    fn sh_bands_give_way_to_the_page_budget_but_records_do_not() {
        let pair = |count, sh_degree| [Embedded { count, sh_degree }; 2];
        // The documented figures: two scenes of 250 000 keep degree 1, two of 125 000 degree 3.
        let mut large = pair(250_000, 3);
        fit_sh_to_budget(&mut large, SH_PAGE_BUDGET_BYTES);
        assert_eq!(large, pair(250_000, 1));
        let mut half = pair(125_000, 3);
        fit_sh_to_budget(&mut half, SH_PAGE_BUDGET_BYTES);
        assert_eq!(half, pair(125_000, 3));
        // Bands drop from the top across scenes; a scene of lower degree keeps its bands meanwhile.
        let mut mixed = [
            Embedded {
                count: 1000,
                sh_degree: 3,
            },
            Embedded {
                count: 1000,
                sh_degree: 1,
            },
        ];
        let degree_2 = mixed[0].page_bytes() - 1000 * (sh_bytes(3) - sh_bytes(2)) * 4 / 3;
        let budget = degree_2 + mixed[1].page_bytes();
        fit_sh_to_budget(&mut mixed, budget);
        assert_eq!((mixed[0].sh_degree, mixed[1].sh_degree), (2, 1));
        // Records alone over the budget: no SH, records kept.
        let mut over = pair(1_000_000, 2);
        fit_sh_to_budget(&mut over, SH_PAGE_BUDGET_BYTES);
        assert_eq!(over, pair(1_000_000, 0));
    }

    #[test]
    fn bands_that_quantise_to_zero_are_left_out() {
        let mut scene = varied(6, 3);
        let k = scene.sh_coeffs();
        let zero_from = |scene: &mut GaussianScene, coefficient: usize| {
            for i in 0..scene.len() {
                scene.sh[i * 3 * k + 3 * coefficient..(i + 1) * 3 * k].fill(0.001);
            }
        };
        zero_from(&mut scene, 9);
        assert_eq!(embedded_sh_degree(&scene, &[0, 1, 2, 3, 4, 5]), 2);
        zero_from(&mut scene, 4);
        assert_eq!(embedded_sh_degree(&scene, &[0, 1, 2, 3, 4, 5]), 1);
        zero_from(&mut scene, 1);
        assert_eq!(embedded_sh_degree(&scene, &[0, 1, 2, 3, 4, 5]), 0);
        assert_eq!(embedded(&scene).0, 0, "no SH bytes in the page");
        // One Gaussian with a band-3 coefficient of 1/128 keeps all three bands.
        scene.sh[2 * 3 * k + 3 * 15 + 1] = 1.0 / 128.0;
        assert_eq!(embedded_sh_degree(&scene, &[0, 1, 2, 3, 4, 5]), 3);
        // ... unless it is not embedded.
        assert_eq!(embedded_sh_degree(&scene, &[0, 1, 3]), 0);
    }

    #[test]
    fn records_round_trip_within_their_quantisation() {
        for degree in [0, 3] {
            let scene = varied(40, degree);
            for i in 0..scene.len() {
                let r = unpack_record(&pack_record(&scene, i));
                assert_eq!(r.position, scene.mean(i), "positions are stored as f32");
                assert_eq!(r.scale, scene.scale(i), "scales are exp(log-scale) as f32");
                let dc = &scene.sh[i * 3 * scene.sh_coeffs()..][..3];
                for (c, (&got, &dc)) in r.color.iter().zip(dc).enumerate() {
                    let want = (0.5 + SH_C0 * dc).clamp(0.0, 1.0);
                    assert!((got - want).abs() <= 0.5 / 255.0 + 1e-6, "colour {i}/{c}");
                }
                assert!((r.opacity - scene.opacity(i)).abs() <= 0.5 / 255.0 + 1e-6);
                let q = &scene.quats[4 * i..4 * i + 4];
                let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
                let sign = q[0].signum();
                for (k, (&got, &qk)) in r.rotation.iter().zip(q).enumerate() {
                    // 1/256 from rounding, 1/128 where a component of 1 is clamped to 255; renormalising
                    // the decoded quaternion moves components by about as much again.
                    let err = (got - sign * qk / n).abs();
                    assert!(err <= 2.0 / 128.0, "quaternion {i}/{k}: error {err}");
                }
            }
        }
    }

    #[test]
    fn rotation_is_quantised_to_the_splat_convention() {
        let mut s = varied(1, 0);
        s.quats = vec![-2.0, 0.0, 0.0, 0.0];
        let rec = pack_record(&s, 0);
        assert_eq!(
            &rec[28..],
            &[255, 128, 128, 128],
            "w = 1 (sign flipped) clamps to 255"
        );
        s.quats = vec![0.0; 4];
        assert_eq!(
            &pack_record(&s, 0)[28..],
            &[255, 128, 128, 128],
            "a zero quaternion is identity"
        );
    }

    #[test]
    fn subset_keeps_the_most_visible_deterministically() {
        let mut scene = varied(500, 0);
        // Two invisible ones: never embedded, whatever the cap.
        scene.opacity_logits[7] = -20.0;
        scene.means[3 * 11] = f32::NAN;
        let all = visible_subset(&scene, usize::MAX);
        assert_eq!(all.len(), 498);
        assert!(!all.contains(&7) && !all.contains(&11));

        let kept = visible_subset(&scene, 100);
        assert_eq!(kept.len(), 100);
        assert_eq!(kept, visible_subset(&scene, 100), "deterministic");
        assert!(kept.windows(2).all(|w| w[0] < w[1]), "scene order");
        let score = |i: usize| {
            let mut ls = scene.log_scales[3 * i..3 * i + 3].to_vec();
            ls.sort_by(f32::total_cmp);
            f64::from(scene.opacity(i)) * f64::from(ls[1] + ls[2]).exp()
        };
        let weakest_kept = kept.iter().map(|&i| score(i)).fold(f64::INFINITY, f64::min);
        let strongest_dropped = all
            .iter()
            .filter(|i| !kept.contains(i))
            .map(|&i| score(i))
            .fold(0.0, f64::max);
        assert!(weakest_kept >= strongest_dropped);

        // Ties go to the lower index.
        let mut same = varied(10, 0);
        same.log_scales.fill(-2.0);
        same.opacity_logits.fill(1.0);
        assert_eq!(visible_subset(&same, 3), vec![0, 1, 2]);
        assert!(visible_subset(&same, 0).is_empty());
    }

    #[test]
    fn base64_matches_rfc_4648() {
        for (input, want) in [
            ("", ""),
            ("f", "Zg=="),
            ("fo", "Zm8="),
            ("foo", "Zm9v"),
            ("foob", "Zm9vYg=="),
            ("fooba", "Zm9vYmE="),
            ("foobar", "Zm9vYmFy"),
        ] {
            assert_eq!(base64(input.as_bytes()), want);
        }
        assert_eq!(base64(&[0xff, 0xfe, 0x3f]), "//4/");
    }

    fn page_for(labels: [&str; 2]) -> String {
        let before = varied(5, 0);
        let after = varied(6, 1);
        let view = InitialView::around(&before);
        viewer_page(
            labels[0],
            &[
                ViewerScene {
                    label: labels[0],
                    scene: &before,
                },
                ViewerScene {
                    label: labels[1],
                    scene: &after,
                },
            ],
            &view,
            &ViewerOptions::default(),
        )
    }

    #[test]
    fn names_are_escaped() {
        let evil = "</script><script>alert(\"x\")</script> & 'q'";
        let html = page_for([evil, "after"]);
        assert!(!html.contains("<script>alert"), "unescaped label");
        assert!(html.contains(
            "&lt;/script&gt;&lt;script&gt;alert(&quot;x&quot;)&lt;/script&gt; &amp; 'q'"
        ));
        // Two data blocks, the config and the script: nothing else opens a script element.
        assert_eq!(html.matches("<script").count(), 4);
        assert!(script_json(&"</script>").contains("\\u003c/script\\u003e"));
    }

    #[test]
    fn page_embeds_every_visible_gaussian_and_states_the_budget() {
        let html = page_for(["before", "after"]);
        // The scene has SH degree 1: its records, then its degree-1 coefficients.
        let tag = "data-label=\"after\" data-sh-degree=\"1\">";
        let start = html.find(tag).unwrap() + tag.len();
        let data = &html[start..start + html[start..].find('<').unwrap()];
        let visible = visible_subset(&varied(6, 1), usize::MAX).len();
        assert_eq!(
            data.len(),
            (visible * (RECORD_BYTES + sh_bytes(1))).div_ceil(3) * 4
        );
        assert!(html.contains("32 bytes per Gaussian, 42.7 in the page as base64"));
        assert!(html.contains("9, 24 or 45 more with SH of degree 1, 2 or 3"));
        // (32 + 45) bytes × 4/3 × 250 000.
        assert!(html.contains("take 10.7 MB, 25.7 MB at degree 3"));
        assert!(html.contains("at most 250\u{202f}000 per scene"));
    }

    #[test]
    fn initial_view_uses_the_first_camera_and_a_point_in_front() {
        let scene = varied(50, 0);
        let cams = orbit_cameras([-1.0; 3], [1.0; 3], 6, 64, 48);
        let view = InitialView::from_cameras(&cams, &scene, None);
        assert_eq!(view.camera, cams[0]);
        // Orbit cameras all look at the bounds' centre.
        assert!(
            view.pivot.iter().all(|v| v.abs() < 1e-6),
            "{:?}",
            view.pivot
        );
        assert!((view.up.iter().map(|v| v * v).sum::<f64>() - 1.0).abs() < 1e-9);
        let given = InitialView::from_cameras(&cams, &scene, Some([0.5, 0.0, 0.0]));
        assert_eq!(given.pivot, [0.5, 0.0, 0.0]);
        // No cameras: an orbit view of the scene, looking at the pivot.
        let around = InitialView::from_cameras(&[], &scene, None);
        let p = around.camera.world_to_camera(around.pivot);
        assert!(
            p[2] > 0.0 && p[0].abs() < 1e-6 && p[1].abs() < 1e-6,
            "{p:?}"
        );
        // Turning about the orbit's world axis keeps the horizon level: the up vector is that axis (the
        // camera looks down at it, so its own up vector is tilted), and the camera's right axis is
        // horizontal.
        let (lo, hi) = robust_bounds(&scene, 0.01).unwrap();
        let world_up = OrbitSettings::default().up.resolve(lo, hi);
        assert_eq!(around.up, world_up);
        let right = around.camera.rotation[0];
        assert!((0..3).map(|a| right[a] * world_up[a]).sum::<f64>().abs() < 1e-9);
        let tilt: f64 = (0..3)
            .map(|a| -around.camera.rotation[1][a] * world_up[a])
            .sum();
        assert!(tilt < 0.999, "the orbit camera looks down at the scene");
    }
}
