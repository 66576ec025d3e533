//! PlayCanvas SOG ("spatially ordered Gaussians", version 2): `meta.json` plus lossless WebP textures,
//! as a folder or bundled in one zip file (`*.sog`). Gaussian i is texel i (row-major) of every per-
//! Gaussian texture, all of the same size (width and height multiples of 4).
//!
//! - `means_l.webp`, `means_u.webp`: low and high bytes of 16-bit x, y, z (RGB) within `means.mins/maxs`,
//!   which bound `sign(v) · ln(|v| + 1)` of each axis.
//! - `quats.webp`: smallest three of the unit quaternion (w, x, y, z) with the largest made positive, each
//!   `255 · (v · √2 · ½ + ½)`, and in alpha `252 +` the index of the largest.
//! - `scales.webp`: for each axis (RGB), an index into `scales.codebook` (256 log-scales).
//! - `sh0.webp`: for each channel (RGB), an index into `sh0.codebook` (256 DC coefficients); alpha is the
//!   opacity · 255.
//! - optional `shN_labels.webp` (palette index, 16 bits in R and G) and `shN_centroids.webp` (64 palette
//!   entries per row; entry e's coefficient j is texel (e mod 64) · K + j of row e / 64, RGB indexing
//!   `shN.codebook`), K = coefficients per channel above DC.
//!
//! Writing keeps the scene's order (the reference tool sorts into Morton order) and fits the 256-entry
//! codebooks by 1-D k-means. Scenes of up to 65 536 Gaussians give every Gaussian its own SH palette
//! entry; larger ones share entries between Gaussians of similar SH (sorted groups, averaged).

use super::codec::{check_quats, largest_component, logit, sigmoid, to_byte, unit_quat};
use crate::scene::sh_coeffs;
use crate::scene::GaussianScene;
use serde::{Deserialize, Serialize};
use std::io::{Read, Write};
use std::path::Path;

pub(crate) const ZIP_MAGIC: &[u8] = b"PK\x03\x04";
const CODEBOOK: usize = 256;
const PALETTE_MAX: usize = 65536;
const PALETTE_ROW: usize = 64;
/// The largest file taken from a SOG zip or folder; real textures are far smaller.
const MAX_FILE_BYTES: u64 = 1 << 30;

#[derive(Serialize, Deserialize)]
struct Meta {
    version: Option<u32>,
    count: u64,
    means: MeansMeta,
    scales: CodebookMeta,
    quats: FilesMeta,
    sh0: CodebookMeta,
    #[serde(rename = "shN", skip_serializing_if = "Option::is_none")]
    sh_n: Option<ShNMeta>,
}

#[derive(Serialize, Deserialize)]
struct MeansMeta {
    mins: [f32; 3],
    maxs: [f32; 3],
    files: Vec<String>,
}

#[derive(Serialize, Deserialize)]
struct CodebookMeta {
    codebook: Vec<f32>,
    files: Vec<String>,
}

#[derive(Serialize, Deserialize)]
struct FilesMeta {
    files: Vec<String>,
}

#[derive(Serialize, Deserialize)]
struct ShNMeta {
    count: u64,
    bands: u32,
    codebook: Vec<f32>,
    files: Vec<String>,
}

fn log_transform(v: f32) -> f32 {
    v.signum() * (v.abs() + 1.0).ln()
}

fn inv_log_transform(v: f32) -> f32 {
    let e = v.abs().exp() - 1.0;
    if v < 0.0 {
        -e
    } else {
        e
    }
}

/// Index order of the three stored components for each largest component of (w, x, y, z).
const QUAT_ORDER: [[usize; 3]; 4] = [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]];

// ---------------------------------------------------------------------------------------------------------
// Reading

/// An RGBA texture.
struct Texture {
    width: usize,
    height: usize,
    rgba: Vec<u8>,
}

/// Decodes a WebP texture of at most `max_texels` texels.
fn decode_webp(name: &str, bytes: &[u8], max_texels: u64) -> Result<Texture, String> {
    let mut reader =
        image::ImageReader::with_format(std::io::Cursor::new(bytes), image::ImageFormat::WebP);
    // The decoder checks the image's claimed size against these limits before allocating: a 40-byte
    // WebP may claim 11000² texels.
    let mut limits = image::Limits::default();
    limits.max_alloc = Some(4 * max_texels);
    reader.limits(limits);
    let img = reader
        .decode()
        .map_err(|e| format!("{name}: not a readable WebP image: {e}"))?
        .to_rgba8();
    Ok(Texture {
        width: img.width() as usize,
        height: img.height() as usize,
        rgba: img.into_raw(),
    })
}

/// Decodes SOG from its `meta.json` and a way to load the files it names.
fn decode_with(
    meta_bytes: &[u8],
    load: &dyn Fn(&str) -> Result<Vec<u8>, String>,
) -> Result<GaussianScene, String> {
    let meta: Meta = serde_json::from_slice(meta_bytes)
        .map_err(|e| format!("meta.json is not SOG metadata: {e}"))?;
    match meta.version {
        Some(2) => {}
        None => return Err("meta.json has no 'version': SOG version 1 is not supported".into()),
        Some(v) => return Err(format!("SOG version {v} is not supported (version 2 is)")),
    }
    // Textures are laid out for the count (`texture_size`); other writers may pad differently, so 4×
    // that (and never less than a 256² texture) is accepted.
    let (w, h) = texture_size(meta.count as usize);
    let max_texels = (w as u64)
        .saturating_mul(h as u64)
        .saturating_mul(4)
        .max(256 * 256);
    // The decoded scene and five textures are held together.
    files::check_allocation(
        GaussianScene::memory_bytes(
            meta.count,
            meta.sh_n.as_ref().map_or(0, |sh| sh.bands.min(3)),
        )
        .saturating_add(meta.count.saturating_mul(5 * 4)),
        &format!("the {} Gaussians meta.json declares", meta.count),
    )?;
    let texture = |files: &[String], i: usize, what: &str| -> Result<Texture, String> {
        let name = files
            .get(i)
            .ok_or_else(|| format!("meta.json names no file for {what}"))?;
        let t = decode_webp(name, &load(name)?, max_texels)?;
        if (t.width * t.height) < meta.count as usize {
            return Err(format!(
                "{name} has {}x{} texels, fewer than the {} Gaussians meta.json declares",
                t.width, t.height, meta.count
            ));
        }
        Ok(t)
    };
    for (what, book) in [
        ("scales", &meta.scales.codebook),
        ("sh0", &meta.sh0.codebook),
    ] {
        if book.is_empty() || book.len() > CODEBOOK || book.iter().any(|v| !v.is_finite()) {
            return Err(format!(
                "the {what} codebook must hold 1 to 256 finite numbers"
            ));
        }
    }
    if meta
        .means
        .mins
        .iter()
        .chain(&meta.means.maxs)
        .any(|v| !v.is_finite())
    {
        return Err("means.mins/maxs must be finite".into());
    }
    // The first texture bounds the count before the scene is allocated.
    let means_l = texture(&meta.means.files, 0, "means (low bytes)")?;
    let means_u = texture(&meta.means.files, 1, "means (high bytes)")?;
    let quats = texture(&meta.quats.files, 0, "quats")?;
    let scales = texture(&meta.scales.files, 0, "scales")?;
    let sh0 = texture(&meta.sh0.files, 0, "sh0")?;
    let n = meta.count as usize;

    let (sh_degree, palette) = match &meta.sh_n {
        None => (0, None),
        Some(sh) => {
            if !(1..=3).contains(&sh.bands) {
                return Err(format!("shN.bands is {}; expected 1, 2 or 3", sh.bands));
            }
            if sh.codebook.is_empty()
                || sh.codebook.len() > CODEBOOK
                || sh.codebook.iter().any(|v| !v.is_finite())
            {
                return Err("the shN codebook must hold 1 to 256 finite numbers".into());
            }
            let centroids = decode_webp(
                sh.files
                    .first()
                    .ok_or("meta.json names no shN centroids file")?,
                &load(&sh.files[0])?,
                // At most PALETTE_MAX centroids of 15 coefficients each (degree 3).
                (PALETTE_MAX * 16) as u64,
            )?;
            let labels = texture(&sh.files, 1, "shN labels")?;
            let rest = sh_coeffs(sh.bands) - 1;
            if centroids.width != PALETTE_ROW * rest {
                return Err(format!(
                    "the shN centroids texture is {} texels wide; {} bands need {}",
                    centroids.width,
                    sh.bands,
                    PALETTE_ROW * rest
                ));
            }
            if (sh.count as usize).div_ceil(PALETTE_ROW) > centroids.height {
                return Err(format!(
                    "the shN centroids texture has {} rows, too few for {} palette entries",
                    centroids.height, sh.count
                ));
            }
            (sh.bands, Some((sh, centroids, labels)))
        }
    };
    let k = sh_coeffs(sh_degree);
    let mut scene = GaussianScene::with_capacity(sh_degree, n);
    let code = |book: &[f32], i: u8, what: &str, g: usize| -> Result<f32, String> {
        book.get(usize::from(i)).copied().ok_or_else(|| {
            format!(
                "Gaussian {g}: {what} index {i} is beyond its codebook of {}",
                book.len()
            )
        })
    };
    for g in 0..n {
        let t = 4 * g;
        for a in 0..3 {
            let v = u16::from_le_bytes([means_l.rgba[t + a], means_u.rgba[t + a]]);
            let (lo, hi) = (meta.means.mins[a], meta.means.maxs[a]);
            let range = if hi - lo == 0.0 { 1.0 } else { hi - lo };
            scene
                .means
                .push(inv_log_transform(lo + range * f32::from(v) / 65535.0));
        }
        for a in 0..3 {
            scene
                .log_scales
                .push(code(&meta.scales.codebook, scales.rgba[t + a], "scale", g)?);
        }
        let tag = quats.rgba[t + 3];
        if !(252..=255).contains(&tag) {
            return Err(format!(
                "Gaussian {g}: quats alpha is {tag}; expected 252-255"
            ));
        }
        let largest = usize::from(tag - 252);
        let mut q = [0.0f32; 4];
        let mut sum_sq = 0.0;
        for (j, &idx) in QUAT_ORDER[largest].iter().enumerate() {
            let v = (f32::from(quats.rgba[t + j]) / 255.0 * 2.0 - 1.0) / std::f32::consts::SQRT_2;
            q[idx] = v;
            sum_sq += v * v;
        }
        q[largest] = (1.0 - sum_sq).max(0.0).sqrt();
        scene.quats.extend_from_slice(&q);
        for ch in 0..3 {
            scene
                .sh
                .push(code(&meta.sh0.codebook, sh0.rgba[t + ch], "colour", g)?);
        }
        scene
            .opacity_logits
            .push(logit(f32::from(sh0.rgba[t + 3]) / 255.0));
        if let Some((sh, centroids, labels)) = &palette {
            let label = usize::from(u16::from_le_bytes([labels.rgba[t], labels.rgba[t + 1]]));
            if label as u64 >= sh.count {
                return Err(format!(
                    "Gaussian {g}: SH palette entry {label} is beyond the palette of {}",
                    sh.count
                ));
            }
            let rest = k - 1;
            let row = label / PALETTE_ROW;
            for j in 0..rest {
                let texel = 4 * (row * centroids.width + (label % PALETTE_ROW) * rest + j);
                for ch in 0..3 {
                    scene
                        .sh
                        .push(code(&sh.codebook, centroids.rgba[texel + ch], "SH", g)?);
                }
            }
        }
    }
    Ok(scene)
}

/// Decodes SOG from in-memory files (`meta.json` and the textures it names).
pub fn decode_files(files: &[(String, Vec<u8>)]) -> Result<GaussianScene, String> {
    let get = |name: &str| -> Result<Vec<u8>, String> {
        files
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, d)| d.clone())
            .ok_or_else(|| format!("{name} is missing"))
    };
    decode_with(&get("meta.json")?, &get)
}

fn read_limited(reader: impl Read, name: &str) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    reader
        .take(MAX_FILE_BYTES + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("cannot read {name}: {e}"))?;
    if out.len() as u64 > MAX_FILE_BYTES {
        return Err(format!("{name} is larger than {MAX_FILE_BYTES} bytes"));
    }
    Ok(out)
}

/// Reads SOG from `meta.json`, loading the textures from the same folder.
pub fn read_folder(meta_path: &Path) -> Result<GaussianScene, String> {
    let dir = meta_path.parent().unwrap_or(Path::new("."));
    let open = |name: &str| -> Result<Vec<u8>, String> {
        // Names are plain file names; anything else could reach outside the folder.
        if name.contains(['/', '\\']) || name == ".." || name.is_empty() {
            return Err(format!(
                "meta.json names '{name}', which is not a plain file name"
            ));
        }
        let file = files::open_regular(&dir.join(name))
            .map_err(|e| format!("cannot open {name} beside meta.json: {e}"))?;
        read_limited(file, name)
    };
    let meta_file =
        files::open_regular(meta_path).map_err(|e| format!("cannot read meta.json: {e}"))?;
    decode_with(&read_limited(meta_file, "meta.json")?, &open)
}

/// The files of the SOG folder `dir` that vcedit may replace, decided by content: `None` when the folder
/// is not a SOG scene (no `meta.json`, one that is not SOG metadata) or holds anything besides
/// `meta.json` and the textures it names (a subfolder, a link, someone else's file). A missing or empty
/// folder is `Some` of nothing. Temporary files of vcedit runs (`files::is_temporary_name`) are passed
/// over: a second run checking the folder at the same time probes it with one.
pub fn replaceable_files(dir: &Path) -> Option<Vec<String>> {
    replaceable(dir).map(|listing| listing.scene)
}

/// A SOG folder's files that vcedit may replace.
#[derive(Default)]
struct Listing {
    /// `meta.json` and the textures it names.
    scene: Vec<String>,
    /// Temporary files of vcedit runs, passed over by the checks.
    temporaries: Vec<String>,
}

/// [`replaceable_files`] and, apart, the temporary files of vcedit runs it passed over.
fn replaceable(dir: &Path) -> Option<Listing> {
    // Another run may swap its folder in while this one is read ([`files::replace_folder`]): the folder
    // opened is then emptied and removed under another name, and its listing fails or names files that
    // are gone. The path names the other run's whole folder by then, so it is read again.
    for _ in 0..4 {
        if let Ok(files) = read_replaceable(dir) {
            return files;
        }
    }
    None
}

/// The folder was swapped out while it was read.
struct Vanished;

/// One reading of [`replaceable_files`].
fn read_replaceable(dir: &Path) -> Result<Option<Listing>, Vanished> {
    use std::io::ErrorKind::NotFound;
    let gone = |e: &std::io::Error| e.kind() == NotFound;
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if gone(&e) => return Ok(Some(Default::default())),
        Err(_) => return Ok(None),
    };
    let mut present = Vec::new();
    let mut temporaries = Vec::new();
    for entry in entries {
        let entry = match entry {
            Ok(entry) => entry,
            Err(e) if gone(&e) => return Err(Vanished),
            Err(_) => return Ok(None),
        };
        match std::fs::symlink_metadata(entry.path()) {
            Ok(m) if m.is_file() => {}
            Err(e) if gone(&e) => return Err(Vanished),
            _ => return Ok(None),
        }
        let Some(name) = entry.file_name().to_str().map(str::to_string) else {
            return Ok(None);
        };
        // Another vcedit run's probe of the folder (its output checks) or a file it is writing: not
        // this scene's, and not someone else's either. Left alone, never listed for replacing.
        if files::is_temporary_name(&name) {
            temporaries.push(name);
            continue;
        }
        present.push(name);
    }
    if present.is_empty() {
        return Ok(Some(Listing {
            scene: present,
            temporaries,
        }));
    }
    let meta_file = match files::open_regular(&dir.join("meta.json")) {
        Ok(f) => f,
        Err(e) if gone(&e) => return Err(Vanished),
        Err(_) => return Ok(None),
    };
    let Some(meta) = read_limited(meta_file, "meta.json")
        .ok()
        .and_then(|bytes| serde_json::from_slice::<Meta>(&bytes).ok())
    else {
        return Ok(None);
    };
    let mut listed = vec!["meta.json".to_string()];
    listed.extend(meta.means.files);
    listed.extend(meta.scales.files);
    listed.extend(meta.quats.files);
    listed.extend(meta.sh0.files);
    listed.extend(meta.sh_n.into_iter().flat_map(|s| s.files));
    Ok(present
        .iter()
        .all(|p| listed.contains(p))
        .then_some(Listing {
            scene: present,
            temporaries,
        }))
}

/// Writes SOG `files` (from [`encode`]) as the folder `dir`, replacing an earlier SOG folder there as a
/// whole (see [`files::replace_folder`]): readers and a second writer see the old scene or the new one,
/// never a mix, and a failure leaves the old one. A folder that is not a SOG folder is refused.
pub fn write_folder(dir: &Path, files: &[(String, Vec<u8>)]) -> Result<u64, String> {
    if replaceable_files(dir).is_none() {
        return Err(not_a_sog_folder(dir));
    }
    let fill = |tmp: &Path| -> std::io::Result<()> {
        for (name, data) in files {
            std::fs::write(tmp.join(name), data)?;
        }
        Ok(())
    };
    // The old folder goes whole: its scene, and any probe another run made in it while it was the
    // output (that run's own clean-up then misses it, as the path names the new folder).
    let discardable = |old: &Path| {
        replaceable(old)
            .map(|listing| [listing.scene, listing.temporaries].concat())
            .unwrap_or_default()
    };
    files::replace_folder(dir, fill, discardable)
        .map_err(|e| format!("cannot write the folder {}: {e}", dir.display()))?;
    Ok(files.iter().map(|(_, d)| d.len() as u64).sum())
}

/// Why `dir` cannot receive a SOG scene.
pub fn not_a_sog_folder(dir: &Path) -> String {
    format!(
        "{} holds files that are not a SOG scene of meta.json and the textures it names; write the SOG folder to a new or empty folder",
        dir.display()
    )
}

/// Reads SOG bundled in a zip file (`meta.json` at the root or in one folder, textures beside it).
pub fn read_zip(path: &Path) -> Result<GaussianScene, String> {
    let file = files::open_regular(path).map_err(|e| format!("cannot read: {e}"))?;
    let archive = std::cell::RefCell::new(
        zip::ZipArchive::new(file).map_err(|e| format!("not a readable zip archive: {e}"))?,
    );
    let meta_name = archive
        .borrow()
        .file_names()
        .filter_map(|n| n.ok().map(|n| n.to_string()))
        .filter(|n| n == "meta.json" || n.ends_with("/meta.json"))
        .min_by_key(|n| n.len())
        .ok_or("the zip archive holds no meta.json")?;
    let prefix = &meta_name[..meta_name.len() - "meta.json".len()];
    let load = |name: &str| -> Result<Vec<u8>, String> {
        let full = format!("{prefix}{name}");
        let mut archive = archive.borrow_mut();
        let entry = archive
            .by_name(&full)
            .map_err(|e| format!("{full} in the zip archive: {e}"))?;
        read_limited(entry, &full)
    };
    let meta = load("meta.json")?;
    decode_with(&meta, &load)
}

// ---------------------------------------------------------------------------------------------------------
// Writing

/// Texture size for `n` Gaussians: both sides multiples of 4, roughly square.
fn texture_size(n: usize) -> (usize, usize) {
    let width = (((n as f64).sqrt() / 4.0).ceil() as usize * 4).max(4);
    let height = (n.div_ceil(width).div_ceil(4) * 4).max(4);
    (width, height)
}

fn encode_webp(rgba: &[u8], width: usize, height: usize) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    image::codecs::webp::WebPEncoder::new_lossless(&mut out)
        .encode(
            rgba,
            width as u32,
            height as u32,
            image::ExtendedColorType::Rgba8,
        )
        .map_err(|e| format!("WebP encoding failed: {e}"))?;
    Ok(out)
}

/// A 1-D codebook of at most 256 values fitted by k-means (exact when there are ≤ 256 distinct values).
struct Codebook {
    /// Ascending.
    values: Vec<f32>,
}

impl Codebook {
    fn fit(data: &[f32]) -> Self {
        let mut sorted: Vec<f32> = data.to_vec();
        sorted.sort_by(f32::total_cmp);
        let mut distinct = sorted.clone();
        distinct.dedup();
        if distinct.len() <= CODEBOOK {
            return Self { values: distinct };
        }
        // Quantile start, then Lloyd steps; on sorted data each cluster is a contiguous range, found by
        // binary search, and its mean comes from prefix sums.
        let prefix: Vec<f64> = std::iter::once(0.0)
            .chain(sorted.iter().scan(0.0f64, |s, &v| {
                *s += f64::from(v);
                Some(*s)
            }))
            .collect();
        let n = sorted.len();
        let mut centres: Vec<f32> = (0..CODEBOOK)
            .map(|j| sorted[((2 * j + 1) * n) / (2 * CODEBOOK)])
            .collect();
        for _ in 0..32 {
            centres.dedup();
            let mut bounds = Vec::with_capacity(centres.len() + 1);
            bounds.push(0);
            for w in centres.windows(2) {
                let mid = 0.5 * (w[0] + w[1]);
                bounds.push(sorted.partition_point(|&v| v < mid));
            }
            bounds.push(n);
            let next: Vec<f32> = bounds
                .windows(2)
                .zip(&centres)
                .map(|(b, &c)| {
                    if b[1] > b[0] {
                        ((prefix[b[1]] - prefix[b[0]]) / (b[1] - b[0]) as f64) as f32
                    } else {
                        c
                    }
                })
                .collect();
            if next == centres {
                break;
            }
            centres = next;
        }
        centres.dedup();
        Self { values: centres }
    }

    /// Index of the nearest codebook value.
    fn index(&self, v: f32) -> u8 {
        let i = self.values.partition_point(|&c| c < v);
        let best = if i == 0 {
            0
        } else if i == self.values.len() || v - self.values[i - 1] <= self.values[i] - v {
            i - 1
        } else {
            i
        };
        best as u8
    }

    /// The codebook as meta.json stores it: 256 entries (the last repeated), as readers expect.
    fn padded(&self) -> Vec<f32> {
        let mut v = self.values.clone();
        let last = *v.last().unwrap_or(&0.0);
        v.resize(CODEBOOK, last);
        v
    }
}

/// SH palette: entries (each `rest · 3` values, coefficient-major, channel inner) and each Gaussian's entry.
fn sh_palette(scene: &GaussianScene) -> (Vec<Vec<f32>>, Vec<usize>) {
    let n = scene.len();
    let k = scene.sh_coeffs();
    let rest_of = |i: usize| scene.sh[3 * k * i + 3..3 * k * (i + 1)].to_vec();
    if n <= PALETTE_MAX {
        return ((0..n).map(rest_of).collect(), (0..n).collect());
    }
    // Too many Gaussians for one entry each: sort by the band-1 coefficients and average runs of
    // consecutive ones, so entries hold similar SH.
    let mut order: Vec<usize> = (0..n).collect();
    let key = |i: usize| {
        let r = &scene.sh[3 * k * i + 3..];
        (r[0] + r[1] + r[2], r[3] + r[4] + r[5], r[6] + r[7] + r[8])
    };
    order.sort_by(|&a, &b| {
        let (ka, kb) = (key(a), key(b));
        ka.0.total_cmp(&kb.0)
            .then(ka.1.total_cmp(&kb.1))
            .then(ka.2.total_cmp(&kb.2))
    });
    let group = n.div_ceil(PALETTE_MAX);
    let mut palette = Vec::with_capacity(PALETTE_MAX);
    let mut labels = vec![0; n];
    for (e, members) in order.chunks(group).enumerate() {
        let mut mean = vec![0.0f32; 3 * (k - 1)];
        for &i in members {
            for (m, v) in mean.iter_mut().zip(rest_of(i)) {
                *m += v / members.len() as f32;
            }
            labels[i] = e;
        }
        palette.push(mean);
    }
    (palette, labels)
}

/// Encodes a scene as SOG files: `meta.json` first, then the textures.
pub fn encode(scene: &GaussianScene) -> Result<Vec<(String, Vec<u8>)>, String> {
    if !(0..=3).contains(&scene.sh_degree) {
        return Err(format!("SH degree {} is above 3", scene.sh_degree));
    }
    check_quats(scene)?;
    let n = scene.len();
    let k = scene.sh_coeffs();
    let (width, height) = texture_size(n);
    if width > 16383 || height > 16383 {
        return Err(format!(
            "{n} Gaussians need {width}x{height} textures, beyond WebP's 16383"
        ));
    }
    let texels = width * height;
    let new_texture = |alpha: u8| {
        let mut t = vec![0u8; 4 * texels];
        t.iter_mut().skip(3).step_by(4).for_each(|a| *a = alpha);
        t
    };

    // Means: 16 bits of the log-transformed coordinate within each axis's range.
    let mut mins = [f32::INFINITY; 3];
    let mut maxs = [f32::NEG_INFINITY; 3];
    for p in scene.means.chunks_exact(3) {
        for a in 0..3 {
            mins[a] = mins[a].min(log_transform(p[a]));
            maxs[a] = maxs[a].max(log_transform(p[a]));
        }
    }
    if n == 0 {
        (mins, maxs) = ([0.0; 3], [0.0; 3]);
    }
    let mut means_l = new_texture(255);
    let mut means_u = new_texture(255);
    for (g, p) in scene.means.chunks_exact(3).enumerate() {
        for a in 0..3 {
            let range = maxs[a] - mins[a];
            let t = if range > 0.0 {
                (log_transform(p[a]) - mins[a]) / range
            } else {
                0.0
            };
            let v = (t * 65535.0).round().clamp(0.0, 65535.0) as u16;
            means_l[4 * g + a] = v.to_le_bytes()[0];
            means_u[4 * g + a] = v.to_le_bytes()[1];
        }
    }

    let mut quats = new_texture(255);
    for g in 0..n {
        let q = unit_quat(&scene.quats, g);
        let largest = largest_component(&q);
        let sign = if q[largest] < 0.0 { -1.0 } else { 1.0 };
        for (j, &idx) in QUAT_ORDER[largest].iter().enumerate() {
            let v = sign * q[idx] * std::f32::consts::SQRT_2;
            quats[4 * g + j] = to_byte(v * 0.5 + 0.5);
        }
        quats[4 * g + 3] = 252 + largest as u8;
    }

    let scale_book = Codebook::fit(&scene.log_scales);
    let mut scales = new_texture(255);
    for (g, s) in scene.log_scales.chunks_exact(3).enumerate() {
        for a in 0..3 {
            scales[4 * g + a] = scale_book.index(s[a]);
        }
    }

    let dc: Vec<f32> = (0..n)
        .flat_map(|g| scene.sh[3 * k * g..3 * k * g + 3].iter().copied())
        .collect();
    let dc_book = Codebook::fit(&dc);
    let mut sh0 = new_texture(255);
    for g in 0..n {
        for ch in 0..3 {
            sh0[4 * g + ch] = dc_book.index(dc[3 * g + ch]);
        }
        sh0[4 * g + 3] = to_byte(sigmoid(scene.opacity_logits[g]));
    }

    let mut meta = Meta {
        version: Some(2),
        count: n as u64,
        means: MeansMeta {
            mins,
            maxs,
            files: vec!["means_l.webp".into(), "means_u.webp".into()],
        },
        scales: CodebookMeta {
            codebook: scale_book.padded(),
            files: vec!["scales.webp".into()],
        },
        quats: FilesMeta {
            files: vec!["quats.webp".into()],
        },
        sh0: CodebookMeta {
            codebook: dc_book.padded(),
            files: vec!["sh0.webp".into()],
        },
        sh_n: None,
    };
    let mut files = vec![
        (
            "means_l.webp".to_string(),
            encode_webp(&means_l, width, height)?,
        ),
        (
            "means_u.webp".to_string(),
            encode_webp(&means_u, width, height)?,
        ),
        (
            "quats.webp".to_string(),
            encode_webp(&quats, width, height)?,
        ),
        (
            "scales.webp".to_string(),
            encode_webp(&scales, width, height)?,
        ),
        ("sh0.webp".to_string(), encode_webp(&sh0, width, height)?),
    ];

    if scene.sh_degree > 0 && n > 0 {
        let rest = k - 1;
        let (palette, labels) = sh_palette(scene);
        let all: Vec<f32> = palette.iter().flatten().copied().collect();
        let book = Codebook::fit(&all);
        let rows = palette.len().div_ceil(PALETTE_ROW);
        let cw = PALETTE_ROW * rest;
        let mut centroids = vec![255u8; 4 * cw * rows];
        for (e, entry) in palette.iter().enumerate() {
            for j in 0..rest {
                let texel = 4 * ((e / PALETTE_ROW) * cw + (e % PALETTE_ROW) * rest + j);
                for ch in 0..3 {
                    centroids[texel + ch] = book.index(entry[3 * j + ch]);
                }
            }
        }
        let mut label_tex = new_texture(255);
        for (g, &label) in labels.iter().enumerate() {
            let [lo, hi] = (label as u16).to_le_bytes();
            label_tex[4 * g] = lo;
            label_tex[4 * g + 1] = hi;
        }
        files.push((
            "shN_centroids.webp".into(),
            encode_webp(&centroids, cw, rows)?,
        ));
        files.push((
            "shN_labels.webp".into(),
            encode_webp(&label_tex, width, height)?,
        ));
        meta.sh_n = Some(ShNMeta {
            count: palette.len() as u64,
            bands: scene.sh_degree,
            codebook: book.padded(),
            files: vec!["shN_centroids.webp".into(), "shN_labels.webp".into()],
        });
    }
    let meta_json = serde_json::to_vec(&meta).map_err(|e| e.to_string())?;
    files.insert(0, ("meta.json".into(), meta_json));
    Ok(files)
}

/// Bundles SOG files into one zip archive (stored: the WebP textures are compressed already).
pub fn zip_files(files: &[(String, Vec<u8>)]) -> Result<Vec<u8>, String> {
    let mut zip = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    let options =
        zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for (name, data) in files {
        zip.start_file(name.as_str(), options)
            .map_err(|e| format!("zip: {e}"))?;
        zip.write_all(data).map_err(|e| format!("zip: {e}"))?;
    }
    Ok(zip.finish().map_err(|e| format!("zip: {e}"))?.into_inner())
}
