//! The INRIA trainer's `cameras.json` (written next to `point_cloud/` in its output folder).
//!
//! A list of `{id, img_name, width, height, position, rotation, fx, fy}`: `rotation` is the
//! camera-to-world rotation (rows) in OpenCV axes, `position` the camera centre. The trainer assumes the
//! principal point at the image centre. No image paths: the output folder holds no images.

use super::{camera_from_c2w, clean_rotation, read_text, CameraError, CameraSet, Intrinsics};
use serde::Deserialize;
use std::path::Path;

#[derive(Deserialize)]
struct Entry {
    img_name: serde_json::Value,
    width: f64,
    height: f64,
    position: [f64; 3],
    rotation: [[f64; 3]; 3],
    fx: f64,
    fy: f64,
}

/// Loads an INRIA `cameras.json`.
pub fn load_inria_cameras(path: &Path) -> Result<CameraSet, CameraError> {
    let text = read_text(path)?;
    parse_inria_cameras(path, &text)
}

/// Parses `text` as the contents of the INRIA `cameras.json` at `path`.
pub fn parse_inria_cameras(path: &Path, text: &str) -> Result<CameraSet, CameraError> {
    let entries: Vec<Entry> = serde_json::from_str(text)
        .map_err(|e| CameraError::invalid(path, format!("not a valid INRIA cameras.json: {e}")))?;
    if entries.is_empty() {
        return Err(CameraError::invalid(path, "the camera list is empty"));
    }
    let mut set = CameraSet::default();
    for (i, e) in entries.into_iter().enumerate() {
        let name = match e.img_name {
            serde_json::Value::String(s) => s,
            other => other.to_string(),
        };
        let bad = |msg: String| CameraError::invalid(path, format!("camera {i} ('{name}'): {msg}"));
        let width = super::dimension(e.width, "width").map_err(bad)?;
        let height = super::dimension(e.height, "height").map_err(bad)?;
        let intrinsics = Intrinsics {
            width,
            height,
            fx: e.fx,
            fy: e.fy,
            cx: width as f64 / 2.0,
            cy: height as f64 / 2.0,
        };
        intrinsics.check().map_err(bad)?;
        let rotation = clean_rotation(e.rotation).map_err(bad)?;
        if e.position.iter().any(|v| !v.is_finite()) {
            return Err(bad("the position is not finite".into()));
        }
        set.cameras
            .push(camera_from_c2w(name, intrinsics, rotation, e.position));
        set.image_paths.push(None);
    }
    Ok(set)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_the_trainer_layout() {
        let text = r#"[{"id": 0, "img_name": "00001", "width": 40, "height": 30,
            "position": [1.0, 2.0, 3.0], "rotation": [[0,0,1],[1,0,0],[0,1,0]], "fy": 35.0, "fx": 36.0}]"#;
        let set = parse_inria_cameras(Path::new("cameras.json"), text).unwrap();
        let cam = &set.cameras[0];
        assert_eq!(cam.name, "00001");
        assert_eq!((cam.fx, cam.fy, cam.cx, cam.cy), (36.0, 35.0, 20.0, 15.0));
        let c = cam.center();
        for a in 0..3 {
            assert!((c[a] - [1.0, 2.0, 3.0][a]).abs() < 1e-12);
        }
        // The camera's forward axis (third column of c2w) is world x, its right axis world y.
        let ahead = cam.world_to_camera([2.0, 2.0, 3.0]);
        assert!(ahead[0].abs() < 1e-12 && ahead[1].abs() < 1e-12 && (ahead[2] - 1.0).abs() < 1e-12);
        let right = cam.world_to_camera([1.0, 3.0, 3.0]);
        assert!((right[0] - 1.0).abs() < 1e-12 && right[1].abs() < 1e-12 && right[2].abs() < 1e-12);
        assert_eq!(set.image_paths, vec![None]);
    }

    #[test]
    fn reports_bad_entries() {
        let p = Path::new("out/cameras.json");
        for (text, want) in [
            ("[]", "empty"),
            ("{}", "not a valid INRIA cameras.json"),
            (
                r#"[{"img_name": "a", "width": 0, "height": 3, "position": [0,0,0], "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1}]"#,
                "camera 0 ('a'): width 0",
            ),
            (
                r#"[{"img_name": "a", "width": 3, "height": 3, "position": [0,0,0], "rotation": [[0,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1}]"#,
                "orthonormal",
            ),
            (
                r#"[{"img_name": "a", "width": 3, "height": 3, "position": [0,0], "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 1, "fy": 1}]"#,
                "expected an array of length 3",
            ),
        ] {
            let e = parse_inria_cameras(p, text).unwrap_err().to_string();
            assert!(
                e.contains("out/cameras.json") && e.contains(want),
                "{want}: {e}"
            );
        }
    }
}
