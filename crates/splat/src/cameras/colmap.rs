//! COLMAP sparse models: `cameras`, `images` and optionally `points3D`, each as `.bin` or `.txt`.
//!
//! COLMAP stores, per image, the world-to-camera rotation as a quaternion (w, x, y, z) and the translation,
//! in OpenCV axes, and uses the same pixel-centre convention as this crate, so poses and intrinsics pass
//! through unchanged. Only the undistorted models PINHOLE and SIMPLE_PINHOLE are accepted; any other model
//! is an error that suggests `colmap image_undistorter`. Image files are resolved as `ROOT/images/NAME`,
//! where ROOT is the dataset folder (the folder holding `sparse/`, or the model folder itself). Cameras
//! come out sorted by image name.

use super::{
    quat_to_matrix, read_bytes, read_text, CameraError, CameraSet, Intrinsics, PointCloud,
};
use crate::cameras::camera::Camera;
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// COLMAP's camera models: (id, name, number of parameters).
const MODELS: [(i32, &str, usize); 12] = [
    (0, "SIMPLE_PINHOLE", 3),
    (1, "PINHOLE", 4),
    (2, "SIMPLE_RADIAL", 4),
    (3, "RADIAL", 5),
    (4, "OPENCV", 8),
    (5, "OPENCV_FISHEYE", 8),
    (6, "FULL_OPENCV", 12),
    (7, "FOV", 5),
    (8, "SIMPLE_RADIAL_FISHEYE", 4),
    (9, "RADIAL_FISHEYE", 5),
    (10, "THIN_PRISM_FISHEYE", 12),
    (11, "RAD_TAN_THIN_PRISM_FISHEYE", 16),
];

/// Whether `dir` holds a COLMAP model (a cameras file and an images file).
pub fn has_model(dir: &Path) -> bool {
    let any = |stem: &str| {
        dir.join(format!("{stem}.bin")).is_file() || dir.join(format!("{stem}.txt")).is_file()
    };
    any("cameras") && any("images")
}

/// `.bin` if present, else `.txt`, else `None`.
fn model_file(dir: &Path, stem: &str) -> Option<PathBuf> {
    ["bin", "txt"]
        .iter()
        .map(|ext| dir.join(format!("{stem}.{ext}")))
        .find(|p| p.is_file())
}

/// The folder whose `images/` holds the pictures: `DIR` for `DIR/sparse/0` and `DIR/sparse`.
fn dataset_root(model_dir: &Path) -> PathBuf {
    let name_is = |p: &Path, n: &str| p.file_name().is_some_and(|f| f == n);
    if let Some(parent) = model_dir.parent() {
        if name_is(parent, "sparse") {
            return parent.parent().unwrap_or(Path::new(".")).to_path_buf();
        }
        if name_is(model_dir, "sparse") {
            return parent.to_path_buf();
        }
    }
    model_dir.to_path_buf()
}

/// Loads the COLMAP model in `model_dir` (the folder holding `cameras.*` and `images.*`).
pub fn load_colmap(model_dir: &Path) -> Result<CameraSet, CameraError> {
    let missing = |stem: &str| CameraError::NotFound {
        path: model_dir.to_path_buf(),
        looked_for: format!("{stem}.bin or {stem}.txt"),
    };
    let cameras_path = model_file(model_dir, "cameras").ok_or_else(|| missing("cameras"))?;
    let images_path = model_file(model_dir, "images").ok_or_else(|| missing("images"))?;
    let intrinsics = if is_bin(&cameras_path) {
        parse_cameras_bin(&cameras_path, &read_bytes(&cameras_path)?)?
    } else {
        parse_cameras_txt(&cameras_path, &read_text(&cameras_path)?)?
    };
    let mut images = if is_bin(&images_path) {
        parse_images_bin(&images_path, &read_bytes(&images_path)?)?
    } else {
        parse_images_txt(&images_path, &read_text(&images_path)?)?
    };
    let points = match model_file(model_dir, "points3D") {
        Some(p) if is_bin(&p) => Some(parse_points_bin(&p, &read_bytes(&p)?)?),
        Some(p) => Some(parse_points_txt(&p, &read_text(&p)?)?),
        None => None,
    };

    images.sort_by(|a, b| a.name.cmp(&b.name));
    let image_dir = dataset_root(model_dir).join("images");
    let mut set = CameraSet {
        points,
        ..Default::default()
    };
    for image in images {
        let Some(k) = intrinsics.get(&image.camera_id) else {
            return Err(CameraError::invalid(
                &images_path,
                format!(
                    "image '{}' refers to camera {}, which {} does not define",
                    image.name,
                    image.camera_id,
                    cameras_path.display()
                ),
            ));
        };
        let rotation = quat_to_matrix(image.qvec).ok_or_else(|| {
            CameraError::invalid(
                &images_path,
                format!(
                    "image '{}' has a zero or non-finite rotation quaternion",
                    image.name
                ),
            )
        })?;
        if image.tvec.iter().any(|v| !v.is_finite()) {
            return Err(CameraError::invalid(
                &images_path,
                format!("image '{}' has a non-finite translation", image.name),
            ));
        }
        let stem = Path::new(&image.name)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| image.name.clone());
        set.cameras.push(Camera {
            name: stem,
            width: k.width,
            height: k.height,
            fx: k.fx,
            fy: k.fy,
            cx: k.cx,
            cy: k.cy,
            rotation,
            translation: image.tvec,
        });
        set.image_paths.push(Some(image_dir.join(&image.name)));
    }
    Ok(set)
}

fn is_bin(p: &Path) -> bool {
    p.extension().is_some_and(|e| e == "bin")
}

/// Turns COLMAP camera parameters into intrinsics, or the right error for the model.
fn intrinsics_for(
    path: &Path,
    camera_id: i64,
    model: &str,
    width: f64,
    height: f64,
    params: &[f64],
) -> Result<Intrinsics, CameraError> {
    let (fx, fy, cx, cy) = match (model, params) {
        ("SIMPLE_PINHOLE", &[f, cx, cy]) => (f, f, cx, cy),
        ("PINHOLE", &[fx, fy, cx, cy]) => (fx, fy, cx, cy),
        ("SIMPLE_PINHOLE" | "PINHOLE", _) => {
            return Err(CameraError::invalid(
                path,
                format!(
                    "camera {camera_id} ({model}) has {} parameters, expected {}",
                    params.len(),
                    if model == "PINHOLE" { 4 } else { 3 }
                ),
            ))
        }
        _ => {
            return Err(CameraError::UnsupportedModel {
                path: path.to_path_buf(),
                camera_id,
                model: model.to_string(),
            })
        }
    };
    let bad = |msg: String| CameraError::invalid(path, format!("camera {camera_id}: {msg}"));
    let k = Intrinsics {
        width: super::dimension(width, "width").map_err(bad)?,
        height: super::dimension(height, "height").map_err(bad)?,
        fx,
        fy,
        cx,
        cy,
    };
    k.check().map_err(bad)?;
    Ok(k)
}

struct ImageRecord {
    name: String,
    camera_id: i64,
    qvec: [f64; 4],
    tvec: [f64; 3],
}

// ---------------------------------------------------------------------------------------------------------
// Binary

/// A bounds-checked little-endian cursor; every short read names what was being read.
struct Bin<'a> {
    path: &'a Path,
    data: &'a [u8],
    pos: usize,
}

impl<'a> Bin<'a> {
    fn take(&mut self, n: usize, what: &dyn Fn() -> String) -> Result<&'a [u8], CameraError> {
        if self.data.len() - self.pos < n {
            return Err(CameraError::invalid(
                self.path,
                format!("the file ends inside {} (truncated?)", what()),
            ));
        }
        let s = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u64(&mut self, what: &dyn Fn() -> String) -> Result<u64, CameraError> {
        Ok(u64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    fn i32(&mut self, what: &dyn Fn() -> String) -> Result<i32, CameraError> {
        Ok(i32::from_le_bytes(self.take(4, what)?.try_into().unwrap()))
    }
    fn f64(&mut self, what: &dyn Fn() -> String) -> Result<f64, CameraError> {
        Ok(f64::from_le_bytes(self.take(8, what)?.try_into().unwrap()))
    }
    fn f64s<const N: usize>(&mut self, what: &dyn Fn() -> String) -> Result<[f64; N], CameraError> {
        let mut out = [0.0; N];
        for v in &mut out {
            *v = self.f64(what)?;
        }
        Ok(out)
    }
    fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }
    /// Reads a record count and checks that `min_record` bytes per record can still follow.
    fn count(&mut self, min_record: usize, what: &str) -> Result<usize, CameraError> {
        let n = self.u64(&|| format!("the number of {what}"))?;
        if n.checked_mul(min_record as u64)
            .is_none_or(|b| b > self.remaining() as u64)
        {
            return Err(CameraError::invalid(
                self.path,
                format!(
                    "declares {n} {what}, but only {} bytes follow (truncated or not a COLMAP file)",
                    self.remaining()
                ),
            ));
        }
        Ok(n as usize)
    }
    fn finish(&self) -> Result<(), CameraError> {
        if self.remaining() != 0 {
            return Err(CameraError::invalid(
                self.path,
                format!(
                    "{} unexpected bytes after the last record",
                    self.remaining()
                ),
            ));
        }
        Ok(())
    }
}

fn parse_cameras_bin(path: &Path, data: &[u8]) -> Result<HashMap<i64, Intrinsics>, CameraError> {
    let mut r = Bin { path, data, pos: 0 };
    let n = r.count(24, "cameras")?;
    let mut out = HashMap::with_capacity(n);
    for i in 0..n {
        let what = || format!("camera record {i}");
        let id = r.i32(&what)? as i64;
        let model_id = r.i32(&what)?;
        let width = r.u64(&what)? as f64;
        let height = r.u64(&what)? as f64;
        let Some(&(_, model, num_params)) = MODELS.iter().find(|m| m.0 == model_id) else {
            return Err(CameraError::invalid(
                path,
                format!("camera {id} has unknown model id {model_id}"),
            ));
        };
        let mut params = Vec::with_capacity(num_params);
        for _ in 0..num_params {
            params.push(r.f64(&what)?);
        }
        let k = intrinsics_for(path, id, model, width, height, &params)?;
        if out.insert(id, k).is_some() {
            return Err(CameraError::invalid(
                path,
                format!("camera {id} is defined twice"),
            ));
        }
    }
    r.finish()?;
    Ok(out)
}

fn parse_images_bin(path: &Path, data: &[u8]) -> Result<Vec<ImageRecord>, CameraError> {
    let mut r = Bin { path, data, pos: 0 };
    // id + qvec + tvec + camera id + empty name + points count.
    let n = r.count(4 + 32 + 24 + 4 + 1 + 8, "images")?;
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let what = || format!("image record {i}");
        let _image_id = r.i32(&what)?;
        let qvec = r.f64s::<4>(&what)?;
        let tvec = r.f64s::<3>(&what)?;
        let camera_id = r.i32(&what)? as i64;
        let rest = &r.data[r.pos..];
        let Some(len) = rest.iter().position(|&b| b == 0) else {
            return Err(CameraError::invalid(
                path,
                format!("the file ends inside the name of image record {i} (truncated?)"),
            ));
        };
        let name = std::str::from_utf8(&rest[..len])
            .map_err(|_| {
                CameraError::invalid(
                    path,
                    format!("image record {i} has a name that is not UTF-8"),
                )
            })?
            .to_string();
        r.pos += len + 1;
        let points = r.count(24, &format!("2D points of image '{name}'"))?;
        r.take(points * 24, &what)?;
        out.push(ImageRecord {
            name,
            camera_id,
            qvec,
            tvec,
        });
    }
    r.finish()?;
    Ok(out)
}

fn parse_points_bin(path: &Path, data: &[u8]) -> Result<PointCloud, CameraError> {
    let mut r = Bin { path, data, pos: 0 };
    // id + xyz + rgb + error + track length.
    let n = r.count(8 + 24 + 3 + 8 + 8, "points")?;
    let mut cloud = PointCloud {
        positions: Vec::with_capacity(n),
        colors: Vec::with_capacity(n),
    };
    for i in 0..n {
        let what = || format!("point record {i}");
        let _id = r.u64(&what)?;
        let xyz = r.f64s::<3>(&what)?;
        let rgb = r.take(3, &what)?;
        let rgb = [rgb[0], rgb[1], rgb[2]];
        let _error = r.f64(&what)?;
        let track = r.count(8, &format!("track entries of point record {i}"))?;
        r.take(track * 8, &what)?;
        push_point(path, &mut cloud, i, xyz, rgb.map(|c| c as f64))?;
    }
    r.finish()?;
    Ok(cloud)
}

fn push_point(
    path: &Path,
    cloud: &mut PointCloud,
    i: usize,
    xyz: [f64; 3],
    rgb255: [f64; 3],
) -> Result<(), CameraError> {
    let p = xyz.map(|v| v as f32);
    if p.iter().any(|v| !v.is_finite()) {
        return Err(CameraError::invalid(
            path,
            format!("point {i} has a non-finite position"),
        ));
    }
    cloud.positions.push(p);
    cloud
        .colors
        .push(rgb255.map(|c| (c / 255.0).clamp(0.0, 1.0) as f32));
    Ok(())
}

// ---------------------------------------------------------------------------------------------------------
// Text

/// Data lines of a COLMAP text file with their 1-based line numbers; comments and blank lines dropped.
fn data_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn number(path: &Path, line: usize, token: &str, what: &str) -> Result<f64, CameraError> {
    token.parse::<f64>().map_err(|_| {
        CameraError::invalid(
            path,
            format!("line {line}: {what} '{token}' is not a number"),
        )
    })
}

fn integer(path: &Path, line: usize, token: &str, what: &str) -> Result<i64, CameraError> {
    token.parse::<i64>().map_err(|_| {
        CameraError::invalid(
            path,
            format!("line {line}: {what} '{token}' is not an integer"),
        )
    })
}

fn parse_cameras_txt(path: &Path, text: &str) -> Result<HashMap<i64, Intrinsics>, CameraError> {
    let mut out = HashMap::new();
    for (line, l) in data_lines(text) {
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 4 {
            return Err(CameraError::invalid(
                path,
                format!(
                    "line {line}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...', got '{l}'"
                ),
            ));
        }
        let id = integer(path, line, t[0], "camera id")?;
        let width = number(path, line, t[2], "width")?;
        let height = number(path, line, t[3], "height")?;
        let params = t[4..]
            .iter()
            .map(|p| number(path, line, p, "parameter"))
            .collect::<Result<Vec<_>, _>>()?;
        let k = intrinsics_for(path, id, t[1], width, height, &params).map_err(|e| match e {
            CameraError::Invalid { path, msg } => CameraError::Invalid {
                path,
                msg: format!("line {line}: {msg}"),
            },
            other => other,
        })?;
        if out.insert(id, k).is_some() {
            return Err(CameraError::invalid(
                path,
                format!("line {line}: camera {id} is defined twice"),
            ));
        }
    }
    Ok(out)
}

fn parse_images_txt(path: &Path, text: &str) -> Result<Vec<ImageRecord>, CameraError> {
    // Each image takes two lines: the pose line and its 2D points (possibly an empty line), so blank lines
    // are only skipped where a pose line is expected, as COLMAP's own reader does.
    let mut out = Vec::new();
    let mut lines = text.lines().enumerate();
    while let Some((i, l)) = lines.next() {
        let line = i + 1;
        let l = l.trim();
        if l.is_empty() || l.starts_with('#') {
            continue;
        }
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 10 {
            return Err(CameraError::invalid(
                path,
                format!(
                    "line {line}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME', got '{}'",
                    l.chars().take(80).collect::<String>()
                ),
            ));
        }
        integer(path, line, t[0], "image id")?;
        let mut v = [0.0; 7];
        for (k, tok) in t[1..8].iter().enumerate() {
            v[k] = number(path, line, tok, "pose value")?;
        }
        let camera_id = integer(path, line, t[8], "camera id")?;
        // Names with spaces survive as the rest of the line.
        let name = after_tokens(l, 9).to_string();
        out.push(ImageRecord {
            name,
            camera_id,
            qvec: [v[0], v[1], v[2], v[3]],
            tvec: [v[4], v[5], v[6]],
        });
        lines.next(); // the 2D points of this image are not needed
    }
    Ok(out)
}

/// What follows the first `n` whitespace-separated tokens of `l`.
fn after_tokens(l: &str, n: usize) -> &str {
    let mut s = l.trim();
    for _ in 0..n {
        let end = s.find(char::is_whitespace).unwrap_or(s.len());
        s = s[end..].trim_start();
    }
    s
}

fn parse_points_txt(path: &Path, text: &str) -> Result<PointCloud, CameraError> {
    let mut cloud = PointCloud::default();
    for (i, (line, l)) in data_lines(text).enumerate() {
        let t: Vec<&str> = l.split_whitespace().collect();
        if t.len() < 8 {
            return Err(CameraError::invalid(
                path,
                format!("line {line}: expected 'POINT3D_ID X Y Z R G B ERROR TRACK...'"),
            ));
        }
        let mut v = [0.0; 6];
        for (k, tok) in t[1..7].iter().enumerate() {
            v[k] = number(path, line, tok, "point value")?;
        }
        push_point(path, &mut cloud, i, [v[0], v[1], v[2]], [v[3], v[4], v[5]]).map_err(
            |e| match e {
                CameraError::Invalid { path, msg } => CameraError::Invalid {
                    path,
                    msg: format!("line {line}: {msg}"),
                },
                other => other,
            },
        )?;
    }
    Ok(cloud)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn images_txt_keeps_names_with_spaces_and_skips_point_lines() {
        let text =
            "# comment\n1 1 0 0 0 1 2 3 5 my photo.jpg\n1.0 2.0 -1\n\n2 1 0 0 0 0 0 0 5 b.png\n\n";
        let imgs = parse_images_txt(Path::new("images.txt"), text).unwrap();
        assert_eq!(imgs.len(), 2);
        assert_eq!(imgs[0].name, "my photo.jpg");
        assert_eq!(imgs[0].tvec, [1.0, 2.0, 3.0]);
        assert_eq!(imgs[1].name, "b.png");
        assert_eq!(imgs[1].camera_id, 5);
    }

    #[test]
    fn dataset_root_follows_sparse_layout() {
        assert_eq!(dataset_root(Path::new("/d/sparse/0")), PathBuf::from("/d"));
        assert_eq!(dataset_root(Path::new("/d/sparse")), PathBuf::from("/d"));
        assert_eq!(
            dataset_root(Path::new("/d/model")),
            PathBuf::from("/d/model")
        );
    }

    #[test]
    fn unsupported_models_are_named() {
        let text = "1 OPENCV 640 480 500 500 320 240 0.1 0.01 0 0\n";
        let e = parse_cameras_txt(Path::new("cameras.txt"), text)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("OPENCV") && e.contains("image_undistorter") && e.contains("cameras.txt"),
            "{e}"
        );
        let e = parse_cameras_txt(Path::new("c.txt"), "1 PINHOLE 640 480 500 320 240\n")
            .unwrap_err()
            .to_string();
        assert!(e.contains("line 1") && e.contains("expected 4"), "{e}");
    }

    #[test]
    fn binary_counts_are_checked_before_allocating() {
        let mut data = u64::MAX.to_le_bytes().to_vec();
        data.extend_from_slice(&[0; 30]);
        for parse in [
            |d: &[u8]| parse_cameras_bin(Path::new("cameras.bin"), d).map(|_| ()),
            |d: &[u8]| parse_images_bin(Path::new("cameras.bin"), d).map(|_| ()),
            |d: &[u8]| parse_points_bin(Path::new("cameras.bin"), d).map(|_| ()),
        ] {
            let e = parse(&data).unwrap_err().to_string();
            assert!(e.contains("declares 18446744073709551615"), "{e}");
        }
    }
}
