//! Opening a scene the way a user names it: a scene file of any supported format, a SOG folder, or an
//! INRIA trainer output folder (the only source that also has cameras).

use crate::cameras::{inria::load_inria_cameras, CameraError, CameraSet};
use crate::formats::ply::{read_ply, PlyError};
use crate::formats::{checked, inria_iteration_ply, read_scene, FormatError};
use crate::scene::GaussianScene;
use std::path::Path;

#[derive(Debug, thiserror::Error)]
pub enum OpenError {
    #[error(transparent)]
    Ply(#[from] PlyError),
    #[error(transparent)]
    Format(#[from] FormatError),
    #[error(transparent)]
    Cameras(#[from] CameraError),
}

/// Opens a scene and, when the source has them, its cameras.
///
/// - An INRIA trainer output folder (no `meta.json`, a `point_cloud/iteration_N/point_cloud.ply`): the
///   highest iteration's PLY plus `cameras.json` at the folder root when present.
/// - Anything else is [`read_scene`]'s, which recognises files and SOG folders by content and says what a
///   path that is none of them is (no cameras).
pub fn open_scene(path: &Path) -> Result<(GaussianScene, Option<CameraSet>), OpenError> {
    if let Some(ply) = inria_iteration_ply(path) {
        let scene = checked(&ply, read_ply(&ply)?)?;
        let cameras_json = path.join("cameras.json");
        let cameras = if cameras_json.is_file() {
            Some(load_inria_cameras(&cameras_json)?)
        } else {
            None
        };
        return Ok((scene, cameras));
    }
    Ok((read_scene(path)?, None))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::formats::ply::write_ply;

    fn tiny(offset: f32) -> GaussianScene {
        GaussianScene {
            sh_degree: 0,
            means: vec![offset, 0.0, 0.0],
            log_scales: vec![-2.0; 3],
            quats: vec![1.0, 0.0, 0.0, 0.0],
            opacity_logits: vec![0.5],
            sh: vec![0.1, 0.2, 0.3],
        }
    }

    #[test]
    fn opens_the_highest_iteration_with_cameras() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path();
        // 7000 < 30000 numerically though not as text; a folder without a ply is ignored.
        write_ply(
            &out.join("point_cloud/iteration_7000/point_cloud.ply"),
            &tiny(1.0),
        )
        .unwrap();
        write_ply(
            &out.join("point_cloud/iteration_30000/point_cloud.ply"),
            &tiny(2.0),
        )
        .unwrap();
        std::fs::create_dir_all(out.join("point_cloud/iteration_90000")).unwrap();
        std::fs::create_dir_all(out.join("point_cloud/iteration_x")).unwrap();
        let (scene, cams) = open_scene(out).unwrap();
        assert_eq!(scene, tiny(2.0));
        assert!(cams.is_none());

        std::fs::write(
            out.join("cameras.json"),
            r#"[{"id": 0, "img_name": "a", "width": 8, "height": 6, "position": [0, 0, -3],
                "rotation": [[1,0,0],[0,1,0],[0,0,1]], "fx": 8, "fy": 8}]"#,
        )
        .unwrap();
        let (_, cams) = open_scene(out).unwrap();
        assert_eq!(cams.unwrap().cameras.len(), 1);

        let (scene, cams) =
            open_scene(&out.join("point_cloud/iteration_7000/point_cloud.ply")).unwrap();
        assert_eq!(scene, tiny(1.0));
        assert!(cams.is_none());
    }

    #[test]
    fn errors_name_the_path() {
        let dir = tempfile::tempdir().unwrap();
        let e = open_scene(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("not a scene") && e.contains(&dir.path().display().to_string()),
            "{e}"
        );
        let missing = dir.path().join("nope.ply");
        let e = open_scene(&missing).unwrap_err().to_string();
        assert!(e.contains("nope.ply") && e.contains("no such file"), "{e}");
        std::fs::write(dir.path().join("cameras.json"), "[1]").unwrap();
        write_ply(
            &dir.path().join("point_cloud/iteration_1/point_cloud.ply"),
            &tiny(0.0),
        )
        .unwrap();
        let e = open_scene(dir.path()).unwrap_err().to_string();
        assert!(e.contains("cameras.json"), "{e}");
    }
}
