//! Posed views from the usual sources, all converted into the one [`Camera`] model of this crate.
//!
//! # Convention
//! Every loader produces OpenCV pinhole cameras: x right, y down, z forward, world-to-camera rotation and
//! translation, intrinsics in pixels. Pixel (i, j) (column i, row j) covers [i, i+1) x [j, j+1) and its
//! centre is (i + 0.5, j + 0.5); a principal point of (w/2, h/2) is the exact image centre. COLMAP and
//! nerfstudio use the same pixel convention, so their intrinsics pass through unchanged, and resizing an
//! image by a factor s scales fx, fy, cx, cy by exactly s (no half-pixel terms).
//!
//! # Sources
//! - COLMAP sparse models ([`colmap`]): `cameras` + `images` (+ `points3D`), `.bin` or `.txt`; only the
//!   undistorted models PINHOLE and SIMPLE_PINHOLE. COLMAP stores world-to-camera poses in OpenCV axes.
//! - nerfstudio / Blender `transforms.json` ([`transforms`]): camera-to-world matrices in OpenGL axes
//!   (x right, y up, z back), converted to OpenCV by negating the camera's y and z axes.
//! - The INRIA trainer's `cameras.json` ([`inria`]): camera-to-world rotation (OpenCV axes) and centre.
//! - Generated orbits around a scene's bounds ([`orbit`]) for a bare `.ply`.
//!
//! [`load_cameras`] detects the source from a file or folder. [`to_working_resolution`] adapts any camera
//! to the editor's working size (square 512 by default) by centre-cropping, then scaling.

pub mod camera;
pub mod colmap;
pub mod inria;
pub mod orbit;
pub mod transforms;

pub use camera::Camera;
pub use orbit::{orbit_cameras, orbit_cameras_with, robust_bounds, OrbitSettings, Up};

use glam::{DMat3, DQuat, DVec3};
use std::path::{Path, PathBuf};

/// Posed views: cameras plus (when the source has them) the image files and a sparse point cloud.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CameraSet {
    pub cameras: Vec<Camera>,
    /// One entry per camera; `None` when the source names no image (INRIA cameras.json, orbits). The file
    /// is not required to exist at load time (rendering needs no images); the loader that reads it reports.
    pub image_paths: Vec<Option<PathBuf>>,
    pub points: Option<PointCloud>,
}

impl CameraSet {
    /// The INRIA trainer's scene normalisation ("nerf++ norm"): the mean camera centre and 1.1 times the
    /// largest distance of a camera centre from it. The radius scales position learning rates and
    /// densification thresholds. `None` without cameras.
    pub fn camera_extent(&self) -> Option<([f64; 3], f64)> {
        if self.cameras.is_empty() {
            return None;
        }
        let centers: Vec<[f64; 3]> = self.cameras.iter().map(Camera::center).collect();
        let n = centers.len() as f64;
        let mean: [f64; 3] = std::array::from_fn(|a| centers.iter().map(|c| c[a]).sum::<f64>() / n);
        let farthest = centers
            .iter()
            .map(|c| (0..3).map(|a| (c[a] - mean[a]).powi(2)).sum::<f64>().sqrt())
            .fold(0.0, f64::max);
        Some((mean, 1.1 * farthest))
    }
}

/// A sparse coloured point cloud (e.g. COLMAP's `points3D`), for initialising a scene.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PointCloud {
    pub positions: Vec<[f32; 3]>,
    /// RGB in [0, 1].
    pub colors: Vec<[f32; 3]>,
}

#[derive(Debug, thiserror::Error)]
pub enum CameraError {
    #[error("{}: cannot read: {err}", path.display())]
    Read { path: PathBuf, err: std::io::Error },
    #[error("{}: {msg}", path.display())]
    Invalid { path: PathBuf, msg: String },
    #[error(
        "{}: camera {camera_id} uses the {model} model, but only PINHOLE and SIMPLE_PINHOLE are supported; \
         undistort the images first (colmap image_undistorter --image_path IMAGES --input_path SPARSE \
         --output_path OUT) and use the undistorted model",
        path.display()
    )]
    UnsupportedModel {
        path: PathBuf,
        camera_id: i64,
        model: String,
    },
    #[error("{}: no cameras found (looked for {looked_for})", path.display())]
    NotFound { path: PathBuf, looked_for: String },
}

impl CameraError {
    pub(crate) fn invalid(path: &Path, msg: impl Into<String>) -> Self {
        CameraError::Invalid {
            path: path.to_path_buf(),
            msg: msg.into(),
        }
    }

    pub(crate) fn read(path: &Path, err: std::io::Error) -> Self {
        CameraError::Read {
            path: path.to_path_buf(),
            err,
        }
    }
}

/// Reads a whole file, mapping failures to a [`CameraError`] naming it.
pub(crate) fn read_bytes(path: &Path) -> Result<Vec<u8>, CameraError> {
    files::read_regular(path).map_err(|e| CameraError::read(path, e))
}

pub(crate) fn read_text(path: &Path) -> Result<String, CameraError> {
    let bytes = read_bytes(path)?;
    String::from_utf8(bytes).map_err(|_| CameraError::invalid(path, "the file is not UTF-8 text"))
}

/// Loads posed views from a file or folder, detecting the format:
///
/// - a folder holding a COLMAP model directly, in `sparse/0` or in `sparse` (`.bin` preferred over `.txt`);
/// - `transforms.json` / `transforms_train.json` in a folder, or any `.json` file whose top level is an
///   object (nerfstudio / Blender);
/// - `cameras.json` in a folder, or any `.json` file whose top level is a list (INRIA trainer output);
/// - a COLMAP `cameras.*` / `images.*` / `points3D.*` file (the model in its folder).
pub fn load_cameras(path: &Path) -> Result<CameraSet, CameraError> {
    if path.is_dir() {
        for candidate in [
            path.to_path_buf(),
            path.join("sparse/0"),
            path.join("sparse"),
        ] {
            if colmap::has_model(&candidate) {
                return colmap::load_colmap(&candidate);
            }
        }
        for name in ["transforms.json", "transforms_train.json"] {
            let p = path.join(name);
            if p.is_file() {
                return transforms::load_transforms(&p);
            }
        }
        let p = path.join("cameras.json");
        if p.is_file() {
            return inria::load_inria_cameras(&p);
        }
        return Err(CameraError::NotFound {
            path: path.to_path_buf(),
            looked_for:
                "a COLMAP model (cameras + images .bin/.txt) in the folder, sparse/0 or sparse; \
                         transforms.json; transforms_train.json; cameras.json"
                    .into(),
        });
    }
    if !path.exists() {
        return Err(CameraError::read(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file or directory"),
        ));
    }
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = file_name.split('.').next().unwrap_or("");
    if matches!(stem, "cameras" | "images" | "points3D")
        && (file_name.ends_with(".bin") || file_name.ends_with(".txt"))
    {
        let dir = path.parent().unwrap_or(Path::new("."));
        return colmap::load_colmap(dir);
    }
    let lower = file_name.to_ascii_lowercase();
    if lower.ends_with(".json") {
        let text = read_text(path)?;
        // A name that says the format decides it, so errors name the format the user meant (a damaged
        // transforms.json whose top level became a list is not an INRIA cameras.json); other names go
        // by content.
        if lower == "cameras.json" {
            return inria::parse_inria_cameras(path, &text);
        }
        if lower.starts_with("transforms") {
            return transforms::parse_transforms(path, &text);
        }
        return match text.trim_start().as_bytes().first() {
            Some(b'[') => inria::parse_inria_cameras(path, &text),
            Some(b'{') => transforms::parse_transforms(path, &text),
            _ => Err(CameraError::invalid(
                path,
                "neither a transforms.json (a JSON object with 'frames') nor an INRIA cameras.json (a JSON list)",
            )),
        };
    }
    Err(CameraError::invalid(
        path,
        "unknown camera file (expected a COLMAP model, transforms.json or cameras.json)",
    ))
}

/// What loading cameras from `path` depends on, for the output checks: `path` itself (a folder with
/// everything in it), and for a COLMAP `cameras.*`/`images.*`/`points3D.*` file the model folder it
/// is read with. (The images a dataset names are inputs of the commands that read them.)
pub fn camera_sources(path: &Path) -> Vec<PathBuf> {
    let mut sources = vec![path.to_path_buf()];
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let stem = name.split('.').next().unwrap_or("");
    if path.is_file() && matches!(stem, "cameras" | "images" | "points3D") {
        sources.push(match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        });
    }
    sources
}

// ---------------------------------------------------------------------------------------------------------
// Working resolution

/// The window of a `width` x `height` image kept when centre-cropping to the aspect of `target_w` x
/// `target_h`: (x0, y0, w, h) in continuous pixel coordinates (may be fractional). Image resampling for a
/// camera passed through [`to_working_resolution`] must use this same window.
pub fn crop_window(width: u32, height: u32, target_w: u32, target_h: u32) -> [f64; 4] {
    let (w, h) = (width as f64, height as f64);
    let target_aspect = target_w as f64 / target_h as f64;
    if w / h > target_aspect {
        let cw = h * target_aspect;
        [(w - cw) / 2.0, 0.0, cw, h]
    } else {
        let ch = w / target_aspect;
        [0.0, (h - ch) / 2.0, w, ch]
    }
}

/// Adapts a camera to a `width` x `height` working image: first centre-crop to the target aspect ratio (the
/// field of view shrinks along the cropped axis; nothing is stretched), then scale the intrinsics to the
/// target size. Thanks to the pixel-centre convention (module docs) both steps are exact in continuous
/// coordinates: a world point seen at continuous pixel (u, v) in the original image is seen at
/// ((u - x0) * s, (v - y0) * s) in the result, with (x0, y0) from [`crop_window`] and s = width / crop width.
pub fn to_working_resolution(cam: &Camera, width: u32, height: u32) -> Camera {
    let [x0, y0, cw, _ch] = crop_window(cam.width, cam.height, width, height);
    let s = width as f64 / cw;
    Camera {
        name: cam.name.clone(),
        width,
        height,
        fx: cam.fx * s,
        fy: cam.fy * s,
        cx: (cam.cx - x0) * s,
        cy: (cam.cy - y0) * s,
        rotation: cam.rotation,
        translation: cam.translation,
    }
}

// ---------------------------------------------------------------------------------------------------------
// Shared pose math

/// Rotation matrix (row-major) of a quaternion (w, x, y, z); `None` if it is zero or not finite. The one
/// quaternion-to-matrix conversion of the camera loaders.
pub(crate) fn quat_to_matrix(q: [f64; 4]) -> Option<[[f64; 3]; 3]> {
    let norm = q.iter().map(|v| v * v).sum::<f64>().sqrt();
    if !norm.is_finite() || norm < 1e-12 {
        return None;
    }
    let [w, x, y, z] = q.map(|v| v / norm);
    Some(rows_of(DMat3::from_quat(DQuat::from_xyzw(x, y, z, w))))
}

/// The rows of `m` (cameras store their rotations row-major; glam's matrices are column-major).
pub(crate) fn rows_of(m: DMat3) -> [[f64; 3]; 3] {
    m.transpose().to_cols_array_2d()
}

/// `v` scaled to unit length; `None` when it is (nearly) zero or not finite. Divides by the length where
/// glam's `normalize` multiplies by its reciprocal, so poses keep the bits they had before glam.
pub(crate) fn unit(v: DVec3) -> Option<DVec3> {
    let n = v.length();
    (n.is_finite() && n > 1e-12).then(|| v / n)
}

/// World-to-camera translation of a camera at `center` with world-to-camera `rotation`: −R·c.
pub(crate) fn translation_of(rotation: &[[f64; 3]; 3], center: DVec3) -> [f64; 3] {
    rotation.map(|row| -DVec3::from(row).dot(center))
}

pub(crate) fn transpose(m: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let mut t = [[0.0; 3]; 3];
    for (i, row) in m.iter().enumerate() {
        for (j, v) in row.iter().enumerate() {
            t[j][i] = *v;
        }
    }
    t
}

fn det(m: &[[f64; 3]; 3]) -> f64 {
    m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
}

/// Checks that `m` is a rotation up to file-precision noise (|M Mᵀ - I| < 1e-3, det +1) and removes that
/// noise (Gram-Schmidt on the rows), because the renderer assumes an exact rotation.
pub(crate) fn clean_rotation(m: [[f64; 3]; 3]) -> Result<[[f64; 3]; 3], String> {
    if m.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the rotation contains NaN or infinite values".into());
    }
    let mut worst: f64 = 0.0;
    for i in 0..3 {
        for j in 0..3 {
            let dot: f64 = (0..3).map(|k| m[i][k] * m[j][k]).sum();
            worst = worst.max((dot - if i == j { 1.0 } else { 0.0 }).abs());
        }
    }
    if worst > 1e-3 {
        return Err(format!(
            "the rotation is not orthonormal (|R Rᵀ - I| = {worst:.3e}; scaled or sheared poses are not supported)"
        ));
    }
    if det(&m) < 0.0 {
        return Err("the rotation is a reflection (determinant -1)".into());
    }
    let [m0, m1, _] = m.map(DVec3::from);
    let r0 = m0 / m0.length();
    let r1 = m1 - m1.dot(r0) * r0;
    let r1 = r1 / r1.length();
    let r2 = r0.cross(r1);
    Ok([r0, r1, r2].map(<[f64; 3]>::from))
}

/// A camera from a camera-to-world rotation (OpenCV axes) and the camera centre.
pub(crate) fn camera_from_c2w(
    name: String,
    intrinsics: Intrinsics,
    c2w_rotation: [[f64; 3]; 3],
    center: [f64; 3],
) -> Camera {
    let rotation = transpose(&c2w_rotation);
    let translation = translation_of(&rotation, DVec3::from(center));
    Camera {
        name,
        width: intrinsics.width,
        height: intrinsics.height,
        fx: intrinsics.fx,
        fy: intrinsics.fy,
        cx: intrinsics.cx,
        cy: intrinsics.cy,
        rotation,
        translation,
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Intrinsics {
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
}

impl Intrinsics {
    /// Checks what a renderer needs: a non-empty image, positive finite focal lengths, finite principal point.
    pub(crate) fn check(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} is empty",
                self.width, self.height
            ));
        }
        if !(self.fx.is_finite() && self.fx > 0.0 && self.fy.is_finite() && self.fy > 0.0) {
            return Err(format!(
                "focal lengths must be positive and finite (fx {}, fy {})",
                self.fx, self.fy
            ));
        }
        if !(self.cx.is_finite() && self.cy.is_finite()) {
            return Err(format!(
                "principal point ({}, {}) is not finite",
                self.cx, self.cy
            ));
        }
        Ok(())
    }
}

/// Image dimensions for a positive integer-valued number read from a text format.
pub(crate) fn dimension(v: f64, what: &str) -> Result<u32, String> {
    if v.is_finite() && v >= 1.0 && v.fract() == 0.0 && v <= u32::MAX as f64 {
        Ok(v as u32)
    } else {
        Err(format!(
            "{what} {v} is not a positive whole number of pixels"
        ))
    }
}

#[cfg(test)]
pub(crate) mod test_util {
    use super::Camera;

    /// Continuous pixel coordinates of a world point, or `None` behind the camera.
    pub fn project(cam: &Camera, p: [f64; 3]) -> Option<[f64; 2]> {
        let q = cam.world_to_camera(p);
        (q[2] > 0.0).then(|| [cam.fx * q[0] / q[2] + cam.cx, cam.fy * q[1] / q[2] + cam.cy])
    }
}

#[cfg(test)]
mod tests {
    use super::test_util::project;
    use super::*;

    fn cam(width: u32, height: u32) -> Camera {
        Camera {
            name: "c".into(),
            width,
            height,
            fx: 300.0,
            fy: 310.0,
            cx: width as f64 / 2.0 + 3.0,
            cy: height as f64 / 2.0 - 2.0,
            rotation: quat_to_matrix([0.9, 0.1, -0.3, 0.2]).unwrap(),
            translation: [0.1, -0.2, 4.0],
        }
    }

    #[test]
    fn working_resolution_crops_then_scales_continuous_coordinates() {
        for (w, h, tw, th) in [
            (640, 480, 512, 512),
            (300, 500, 512, 512),
            (200, 200, 64, 32),
            (100, 80, 50, 40),
        ] {
            let src = cam(w, h);
            let dst = to_working_resolution(&src, tw, th);
            let [x0, y0, cw, ch] = crop_window(w, h, tw, th);
            let s = tw as f64 / cw;
            assert!((th as f64 / ch - s).abs() < 1e-12, "aspect preserved");
            for p in [[0.3, 0.2, 0.1], [-0.5, 0.4, 0.0], [0.0, 0.0, 0.5]] {
                let a = project(&src, p).unwrap();
                let b = project(&dst, p).unwrap();
                assert!((b[0] - (a[0] - x0) * s).abs() < 1e-9);
                assert!((b[1] - (a[1] - y0) * s).abs() < 1e-9);
            }
        }
    }

    #[test]
    fn working_resolution_narrows_fov_only_along_cropped_axis() {
        let mut src = cam(800, 400);
        src.cx = 400.0;
        src.cy = 200.0;
        let dst = to_working_resolution(&src, 512, 512);
        let (fx0, fy0) = src.fov();
        let (fx1, fy1) = dst.fov();
        assert!((fy1 - fy0).abs() < 1e-12, "vertical FoV kept");
        assert!(fx1 < fx0 - 0.1, "horizontal FoV cropped");
        assert!((dst.cx - 256.0).abs() < 1e-12 && (dst.cy - 256.0).abs() < 1e-12);
        assert!((dst.fx - 300.0 * 512.0 / 400.0).abs() < 1e-9);
    }

    #[test]
    fn clean_rotation_accepts_noise_and_rejects_non_rotations() {
        let r = quat_to_matrix([0.3, -0.2, 0.5, 0.7]).unwrap();
        let mut noisy = r;
        noisy[1][2] += 1e-6;
        let c = clean_rotation(noisy).unwrap();
        for i in 0..3 {
            for j in 0..3 {
                assert!((c[i][j] - r[i][j]).abs() < 1e-5);
                let dot: f64 = (0..3).map(|k| c[i][k] * c[j][k]).sum();
                assert!((dot - if i == j { 1.0 } else { 0.0 }).abs() < 1e-12);
            }
        }
        let mut scaled = r;
        scaled[0] = scaled[0].map(|v| v * 2.0);
        assert!(clean_rotation(scaled).unwrap_err().contains("orthonormal"));
        let mut mirrored = r;
        mirrored[2] = mirrored[2].map(|v| -v);
        assert!(clean_rotation(mirrored).unwrap_err().contains("reflection"));
        assert!(quat_to_matrix([0.0; 4]).is_none());
        assert!(quat_to_matrix([f64::NAN, 0.0, 0.0, 1.0]).is_none());
    }

    #[test]
    fn quaternion_matches_axis_angle() {
        // 90 degrees about z: x -> y.
        let h = std::f64::consts::FRAC_1_SQRT_2;
        let r = quat_to_matrix([h, 0.0, 0.0, h]).unwrap();
        let x = [1.0, 0.0, 0.0];
        let rx: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| r[i][j] * x[j]).sum())
            .collect();
        assert!((rx[0]).abs() < 1e-12 && (rx[1] - 1.0).abs() < 1e-12 && rx[2].abs() < 1e-12);
    }

    #[test]
    fn camera_extent_is_the_inria_normalisation() {
        let at =
            |c: [f64; 3]| orbit::look_at(String::new(), c, [0.0; 3], [0.0, 0.0, 1.0], 8, 8, 8.0);
        let set = CameraSet {
            cameras: vec![
                at([2.0, 0.0, 1.0]),
                at([-2.0, 0.0, 1.0]),
                at([0.0, 4.0, 1.0]),
            ],
            ..Default::default()
        };
        let (mean, radius) = set.camera_extent().unwrap();
        let want = [0.0, 4.0 / 3.0, 1.0];
        for a in 0..3 {
            assert!((mean[a] - want[a]).abs() < 1e-12);
        }
        assert!((radius - 1.1 * (8.0f64 / 3.0)).abs() < 1e-12);
        assert!(CameraSet::default().camera_extent().is_none());
    }

    #[test]
    fn load_cameras_reports_missing_and_unknown() {
        let dir = tempfile::tempdir().unwrap();
        let e = load_cameras(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("no cameras found") && e.contains("sparse/0"),
            "{e}"
        );
        let p = dir.path().join("nope.json");
        let e = load_cameras(&p).unwrap_err().to_string();
        assert!(e.contains("nope.json"), "{e}");
        std::fs::write(&p, "42").unwrap();
        let e = load_cameras(&p).unwrap_err().to_string();
        assert!(e.contains("neither a transforms.json"), "{e}");
        let p = dir.path().join("x.yaml");
        std::fs::write(&p, "a: 1").unwrap();
        let e = load_cameras(&p).unwrap_err().to_string();
        assert!(
            e.contains("x.yaml") && e.contains("unknown camera file"),
            "{e}"
        );
    }

    /// A file named as one format is read as that format, so its errors name it (issue 69: a
    /// transforms.json was called an INRIA cameras.json, and the reverse).
    #[test]
    fn a_json_named_for_its_format_is_described_as_that_format() {
        let dir = tempfile::tempdir().unwrap();
        let transforms = dir.path().join("transforms.json");
        std::fs::write(&transforms, "[1, 2]").unwrap();
        let e = load_cameras(&transforms).unwrap_err().to_string();
        assert!(
            e.contains("not a valid transforms.json") && !e.contains("INRIA"),
            "{e}"
        );
        let cameras = dir.path().join("cameras.json");
        std::fs::write(&cameras, r#"{"frames": []}"#).unwrap();
        let e = load_cameras(&cameras).unwrap_err().to_string();
        assert!(e.contains("not a valid INRIA cameras.json"), "{e}");
        // Other names go by content.
        let other = dir.path().join("poses.json");
        std::fs::write(&other, "[1, 2]").unwrap();
        let e = load_cameras(&other).unwrap_err().to_string();
        assert!(e.contains("INRIA"), "{e}");
    }
}
