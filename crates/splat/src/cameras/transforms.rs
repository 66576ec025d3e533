//! nerfstudio / Blender (NeRF synthetic) `transforms.json`.
//!
//! Intrinsics come from the top level, overridden per frame: `fl_x`/`fl_y`/`cx`/`cy`/`w`/`h`, or
//! `camera_angle_x` (and optionally `camera_angle_y`), the full horizontal field of view in radians. Missing
//! `w`/`h` are read from the image file's header; a missing `fl_y` equals `fl_x`; a missing principal
//! point is the image centre. Lens distortion (non-zero `k1..k4`, `p1`, `p2`) and non-pinhole camera
//! models are rejected: undistort first.
//!
//! `transform_matrix` is camera-to-world in OpenGL axes (x right, y up, z back); negating the camera's y
//! and z axes gives the OpenCV camera used everywhere in this crate. `file_path` is relative to the json's
//! folder, with or without an extension (Blender writes `./train/r_0` for `train/r_0.png`).

use super::{camera_from_c2w, clean_rotation, read_text, CameraError, CameraSet, Intrinsics};
use serde::Deserialize;
use std::path::{Component, Path, PathBuf};

/// Extensions tried, in order, when `file_path` does not name an existing file.
const IMAGE_EXTENSIONS: [&str; 5] = ["png", "jpg", "jpeg", "PNG", "JPG"];

#[derive(Clone, Copy, Debug, Default, Deserialize)]
struct IntrinsicFields {
    camera_angle_x: Option<f64>,
    camera_angle_y: Option<f64>,
    fl_x: Option<f64>,
    fl_y: Option<f64>,
    cx: Option<f64>,
    cy: Option<f64>,
    w: Option<f64>,
    h: Option<f64>,
    k1: Option<f64>,
    k2: Option<f64>,
    k3: Option<f64>,
    k4: Option<f64>,
    p1: Option<f64>,
    p2: Option<f64>,
}

impl IntrinsicFields {
    /// These values, with the gaps filled from `fallback`.
    fn or(self, fallback: &IntrinsicFields) -> IntrinsicFields {
        IntrinsicFields {
            camera_angle_x: self.camera_angle_x.or(fallback.camera_angle_x),
            camera_angle_y: self.camera_angle_y.or(fallback.camera_angle_y),
            fl_x: self.fl_x.or(fallback.fl_x),
            fl_y: self.fl_y.or(fallback.fl_y),
            cx: self.cx.or(fallback.cx),
            cy: self.cy.or(fallback.cy),
            w: self.w.or(fallback.w),
            h: self.h.or(fallback.h),
            k1: self.k1.or(fallback.k1),
            k2: self.k2.or(fallback.k2),
            k3: self.k3.or(fallback.k3),
            k4: self.k4.or(fallback.k4),
            p1: self.p1.or(fallback.p1),
            p2: self.p2.or(fallback.p2),
        }
    }
}

#[derive(Deserialize)]
struct TransformsFile {
    #[serde(flatten)]
    intrinsics: IntrinsicFields,
    camera_model: Option<String>,
    frames: Vec<Frame>,
}

#[derive(Deserialize)]
struct Frame {
    file_path: String,
    transform_matrix: Vec<Vec<f64>>,
    #[serde(flatten)]
    intrinsics: IntrinsicFields,
}

/// Loads a `transforms.json` file.
pub fn load_transforms(path: &Path) -> Result<CameraSet, CameraError> {
    let text = read_text(path)?;
    parse_transforms(path, &text)
}

/// Parses `text` as the contents of the `transforms.json` at `path` (images resolve against its folder).
pub fn parse_transforms(path: &Path, text: &str) -> Result<CameraSet, CameraError> {
    let file: TransformsFile = serde_json::from_str(text)
        .map_err(|e| CameraError::invalid(path, format!("not a valid transforms.json: {e}")))?;
    if let Some(model) = &file.camera_model {
        if !matches!(model.as_str(), "OPENCV" | "PINHOLE" | "SIMPLE_PINHOLE") {
            return Err(CameraError::UnsupportedModel {
                path: path.to_path_buf(),
                camera_id: -1,
                model: model.clone(),
            });
        }
    }
    if file.frames.is_empty() {
        return Err(CameraError::invalid(path, "'frames' is empty"));
    }
    let base = path.parent().unwrap_or(Path::new("."));
    let mut set = CameraSet::default();
    for (i, frame) in file.frames.iter().enumerate() {
        let bad = |msg: String| {
            CameraError::invalid(path, format!("frame {i} ('{}'): {msg}", frame.file_path))
        };
        let image = resolve_image(base, &frame.file_path);
        let k = frame.intrinsics.or(&file.intrinsics);
        let intrinsics = intrinsics(&k, &image).map_err(bad)?;
        let (rotation, center) = opencv_pose(&frame.transform_matrix).map_err(bad)?;
        let name = Path::new(&frame.file_path)
            .file_stem()
            .map(|s| s.to_string_lossy().into_owned())
            .unwrap_or_else(|| format!("frame_{i:04}"));
        set.cameras
            .push(camera_from_c2w(name, intrinsics, rotation, center));
        set.image_paths.push(Some(image));
    }
    Ok(set)
}

/// `file_path` relative to `base`; when it does not exist as given, the first existing file with an image
/// extension appended, else (for extension-less paths) the `.png` Blender implies.
fn resolve_image(base: &Path, file_path: &str) -> PathBuf {
    // Drop "./" components so paths print cleanly.
    let relative: PathBuf = Path::new(file_path)
        .components()
        .filter(|c| !matches!(c, Component::CurDir))
        .collect();
    let direct = base.join(&relative);
    if direct.is_file() {
        return direct;
    }
    let with_ext = |ext: &str| {
        let mut s = direct.clone().into_os_string();
        s.push(".");
        s.push(ext);
        PathBuf::from(s)
    };
    if let Some(found) = IMAGE_EXTENSIONS
        .iter()
        .map(|e| with_ext(e))
        .find(|p| p.is_file())
    {
        return found;
    }
    if direct.extension().is_none() {
        with_ext("png")
    } else {
        direct
    }
}

fn intrinsics(k: &IntrinsicFields, image: &Path) -> Result<Intrinsics, String> {
    let distortion = [
        ("k1", k.k1),
        ("k2", k.k2),
        ("k3", k.k3),
        ("k4", k.k4),
        ("p1", k.p1),
        ("p2", k.p2),
    ];
    if let Some((name, Some(v))) = distortion.iter().find(|(_, v)| v.is_some_and(|v| v != 0.0)) {
        return Err(format!(
            "lens distortion ({name} = {v}) is not supported; undistort the images first \
             (e.g. colmap image_undistorter) and use pinhole intrinsics"
        ));
    }
    let (width, height) = match (k.w, k.h) {
        (Some(w), Some(h)) => (super::dimension(w, "w")?, super::dimension(h, "h")?),
        _ => image::image_dimensions(image).map_err(|e| {
            format!(
                "no 'w'/'h' given and the image size cannot be read from {}: {e}",
                image.display()
            )
        })?,
    };
    let (w, h) = (width as f64, height as f64);
    let from_angle = |size: f64, angle: f64| 0.5 * size / (0.5 * angle).tan();
    let check_angle = |name: &str, a: f64| {
        if a.is_finite() && a > 0.0 && a < std::f64::consts::PI {
            Ok(a)
        } else {
            Err(format!(
                "{name} = {a} is not a field of view in (0, pi) radians"
            ))
        }
    };
    let fx = match (k.fl_x, k.camera_angle_x) {
        (Some(f), _) => f,
        (None, Some(a)) => from_angle(w, check_angle("camera_angle_x", a)?),
        (None, None) => return Err("no focal length ('fl_x' or 'camera_angle_x')".into()),
    };
    let fy = match (k.fl_y, k.camera_angle_y) {
        (Some(f), _) => f,
        (None, Some(a)) => from_angle(h, check_angle("camera_angle_y", a)?),
        (None, None) => fx,
    };
    let intrinsics = Intrinsics {
        width,
        height,
        fx,
        fy,
        cx: k.cx.unwrap_or(w / 2.0),
        cy: k.cy.unwrap_or(h / 2.0),
    };
    intrinsics.check()?;
    Ok(intrinsics)
}

/// Camera-to-world rotation in OpenCV axes and the camera centre, from an OpenGL `transform_matrix`.
fn opencv_pose(m: &[Vec<f64>]) -> Result<([[f64; 3]; 3], [f64; 3]), String> {
    if m.len() < 3 || m.len() > 4 || m.iter().any(|row| row.len() != 4) {
        return Err("transform_matrix must be 4x4 (or 3x4)".into());
    }
    let mut rotation = [[0.0; 3]; 3];
    let mut center = [0.0; 3];
    for i in 0..3 {
        // Columns are the camera axes in world space; OpenGL's y (up) and z (back) flip for OpenCV.
        rotation[i] = [m[i][0], -m[i][1], -m[i][2]];
        center[i] = m[i][3];
    }
    if center.iter().any(|v| !v.is_finite()) {
        return Err("transform_matrix has a non-finite translation".into());
    }
    Ok((clean_rotation(rotation)?, center))
}

#[cfg(test)]
mod tests {
    use super::super::test_util::project;
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn opengl_camera_looking_down_minus_z_becomes_opencv() {
        // Identity c2w in OpenGL: camera at (0,0,5) looking towards -z with y up.
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            dir.path(),
            "transforms.json",
            r#"{"fl_x": 100, "w": 200, "h": 100, "frames": [{"file_path": "a",
                "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,5],[0,0,0,1]]}]}"#,
        );
        let set = parse_transforms(&p, &std::fs::read_to_string(&p).unwrap()).unwrap();
        let cam = &set.cameras[0];
        assert_eq!(cam.center(), [0.0, 0.0, 5.0]);
        // World origin is straight ahead, at the principal point.
        let c = project(cam, [0.0, 0.0, 0.0]).unwrap();
        assert!((c[0] - 100.0).abs() < 1e-12 && (c[1] - 50.0).abs() < 1e-12);
        // World +y (up) appears above the centre (smaller row), world +x to the right.
        assert!(project(cam, [0.0, 1.0, 0.0]).unwrap()[1] < 50.0);
        assert!(project(cam, [1.0, 0.0, 0.0]).unwrap()[0] > 100.0);
        assert_eq!(cam.fy, 100.0);
        assert_eq!(set.image_paths[0], Some(dir.path().join("a.png")));
    }

    #[test]
    fn per_frame_overrides_and_camera_angle() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            dir.path(),
            "t.json",
            r#"{"camera_angle_x": 1.0, "w": 64, "h": 32, "frames": [
                {"file_path": "./x/a.jpg", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
                {"file_path": "b", "fl_x": 50, "fl_y": 60, "cx": 30, "h": 40,
                 "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#,
        );
        let set = parse_transforms(&p, &std::fs::read_to_string(&p).unwrap()).unwrap();
        let a = &set.cameras[0];
        assert!((a.fx - 32.0 / 0.5f64.tan()).abs() < 1e-12);
        assert_eq!(
            (a.fy, a.cx, a.cy, a.width, a.height),
            (a.fx, 32.0, 16.0, 64, 32)
        );
        assert_eq!(a.name, "a");
        assert_eq!(set.image_paths[0], Some(dir.path().join("x/a.jpg")));
        let b = &set.cameras[1];
        assert_eq!(
            (b.fx, b.fy, b.cx, b.cy, b.width, b.height),
            (50.0, 60.0, 30.0, 20.0, 64, 40)
        );
    }

    #[test]
    fn size_comes_from_the_image_when_not_given() {
        let dir = tempfile::tempdir().unwrap();
        crate::image::Image::new(12, 7, 3)
            .save_png(&dir.path().join("img.png"))
            .unwrap();
        let p = write(
            dir.path(),
            "transforms.json",
            r#"{"camera_angle_x": 0.7, "frames": [{"file_path": "img",
                "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]},
                {"file_path": "missing", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}"#,
        );
        let e = load_transforms(&p).unwrap_err().to_string();
        assert!(
            e.contains("frame 1 ('missing')") && e.contains("missing.png"),
            "{e}"
        );
        let text = std::fs::read_to_string(&p).unwrap();
        let first_only = text.replace(
            r#",
                {"file_path": "missing", "transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}"#,
            "",
        );
        let set = parse_transforms(&p, &first_only).unwrap();
        assert_eq!((set.cameras[0].width, set.cameras[0].height), (12, 7));
    }

    #[test]
    fn rejects_distortion_models_and_bad_matrices() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("transforms.json");
        let ident = "[[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]";
        let cases = [
            (format!(r#"{{"fl_x":1,"w":2,"h":2,"k1":0.1,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "k1 = 0.1"),
            (format!(r#"{{"camera_model":"OPENCV_FISHEYE","fl_x":1,"w":2,"h":2,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "OPENCV_FISHEYE"),
            (r#"{"fl_x":1,"w":2,"h":2,"frames":[{"file_path":"a","transform_matrix":[[2,0,0,0],[0,1,0,0],[0,0,1,0]]}]}"#.to_string(), "orthonormal"),
            (r#"{"fl_x":1,"w":2,"h":2,"frames":[{"file_path":"a","transform_matrix":[[1,0,0],[0,1,0],[0,0,1]]}]}"#.to_string(), "4x4"),
            (format!(r#"{{"w":2,"h":2,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "no focal length"),
            (format!(r#"{{"fl_x":-3,"w":2,"h":2,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "positive"),
            (format!(r#"{{"camera_angle_x":4,"w":2,"h":2,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "camera_angle_x = 4"),
            (format!(r#"{{"fl_x":1,"w":2.5,"h":2,"frames":[{{"file_path":"a","transform_matrix":{ident}}}]}}"#), "w 2.5"),
            (r#"{"fl_x":1,"w":2,"h":2,"frames":[]}"#.to_string(), "'frames' is empty"),
            (r#"{"fl_x":1,"w":2,"h":2}"#.to_string(), "missing field `frames`"),
            (r#"{"fl_x":"a","frames":[]}"#.to_string(), "invalid type"),
        ];
        for (text, want) in cases {
            let e = parse_transforms(&p, &text).unwrap_err().to_string();
            assert!(
                e.contains(want) && e.contains("transforms.json"),
                "{want}: {e}"
            );
        }
    }
}
