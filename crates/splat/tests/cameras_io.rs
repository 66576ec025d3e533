//! Camera loaders: the same cameras written as COLMAP (.txt and .bin), transforms.json and INRIA
//! cameras.json must load to the same OpenCV cameras; layouts are detected; bad files give clear errors;
//! corrupted files never panic; the real Blender dataset loads when present.

#[path = "support/camera_files.rs"]
mod camera_files;

use camera_files::*;
use proptest::prelude::*;
use splat::cameras::{load_cameras, to_working_resolution, CameraSet};
use splat::Camera;
use std::path::PathBuf;

fn assert_close(a: &Camera, b: &Camera) {
    assert_eq!((a.width, a.height, &a.name), (b.width, b.height, &b.name));
    let close = |x: f64, y: f64| (x - y).abs() < 1e-9 * (1.0 + x.abs());
    for (x, y) in [(a.fx, b.fx), (a.fy, b.fy), (a.cx, b.cx), (a.cy, b.cy)] {
        assert!(close(x, y), "{a:?}\n{b:?}");
    }
    for i in 0..3 {
        assert!(close(a.translation[i], b.translation[i]), "{a:?}\n{b:?}");
        for j in 0..3 {
            assert!(close(a.rotation[i][j], b.rotation[i][j]), "{a:?}\n{b:?}");
        }
    }
}

fn project(cam: &Camera, p: [f64; 3]) -> [f64; 3] {
    let q = cam.world_to_camera(p);
    [
        cam.fx * q[0] / q[2] + cam.cx,
        cam.fy * q[1] / q[2] + cam.cy,
        q[2],
    ]
}

#[test]
fn colmap_txt_bin_transforms_and_inria_agree() {
    let dir = tempfile::tempdir().unwrap();
    let vs = views();
    let txt_root = dir.path().join("txt");
    colmap_txt(&txt_root.join("sparse/0"), &vs);
    let bin_root = dir.path().join("bin");
    colmap_bin(&bin_root.join("sparse"), &vs);
    let tf = dir.path().join("transforms.json");
    transforms_json(&tf, &vs);

    let from_txt = load_cameras(&txt_root).unwrap();
    let from_bin = load_cameras(&bin_root).unwrap();
    let from_tf = load_cameras(&tf).unwrap();
    assert_eq!(from_txt.cameras.len(), 2);
    // Sorted by image name; names are stems.
    assert_eq!(from_txt.cameras[0].name, "a");
    assert_eq!(from_txt.image_paths[0], Some(txt_root.join("images/a.png")));
    assert_eq!(from_bin.image_paths[1], Some(bin_root.join("images/b.png")));
    // The transforms paths name files that do not exist: the .png Blender implies is appended.
    let tf_a = from_tf.cameras.iter().position(|c| c.name == "a").unwrap();
    assert_eq!(
        from_tf.image_paths[tf_a],
        Some(dir.path().join("images/a.png"))
    );

    for cam in &from_txt.cameras {
        let same_bin = from_bin
            .cameras
            .iter()
            .find(|c| c.name == cam.name)
            .unwrap();
        let same_tf = from_tf.cameras.iter().find(|c| c.name == cam.name).unwrap();
        assert_close(cam, same_bin);
        assert_close(cam, same_tf);
    }

    // Points: positions exact, colours scaled to [0, 1].
    for set in [&from_txt, &from_bin] {
        let pts = set.points.as_ref().unwrap();
        assert_eq!(pts.positions, vec![[0.5, -1.0, 2.0], [1e-3, 2.0, -3.0]]);
        assert_eq!(pts.colors[0], [1.0, 0.0, 0.2]);
        assert_eq!(pts.colors[1][2], 1.0);
    }
    assert!(from_tf.points.is_none());

    // INRIA cameras.json assumes a centred principal point; view "a" has one.
    let inria = dir.path().join("cameras.json");
    inria_json(&inria, &vs);
    let from_inria = load_cameras(&inria).unwrap();
    let a_inria = from_inria.cameras.iter().find(|c| c.name == "a").unwrap();
    assert_close(&from_txt.cameras[0], a_inria);
    assert_eq!(from_inria.image_paths, vec![None, None]);
}

#[test]
fn loaded_cameras_follow_the_opencv_convention() {
    // One view with an exactly known geometry: camera at the origin looking down world +z.
    let dir = tempfile::tempdir().unwrap();
    let view = View {
        name: "only.png",
        width: 101,
        height: 51,
        fx: 100.0,
        fy: 100.0,
        cx: 50.5,
        cy: 25.5,
        pose: Pose {
            q: [1.0, 0.0, 0.0, 0.0],
            center: [0.0, 0.0, 0.0],
        },
    };
    colmap_txt(dir.path(), std::slice::from_ref(&view));
    let set = load_cameras(dir.path()).unwrap();
    let cam = &set.cameras[0];
    // A point on the optical axis lands on the centre of the centre pixel (50, 25): (50.5, 25.5).
    let c = project(cam, [0.0, 0.0, 2.0]);
    assert_eq!([c[0], c[1]], [50.5, 25.5]);
    // +x is right, +y is down.
    let p = project(cam, [0.01, 0.02, 1.0]);
    assert!((p[0] - 51.5).abs() < 1e-12 && (p[1] - 27.5).abs() < 1e-12);
    // The working square crops the long side: the centre stays the centre, the FoV shrinks horizontally.
    let w = to_working_resolution(cam, 512, 512);
    let c = project(&w, [0.0, 0.0, 2.0]);
    assert!((c[0] - 256.0).abs() < 1e-9 && (c[1] - 256.0).abs() < 1e-9);
    assert!((w.fov().1 - cam.fov().1).abs() < 1e-12);
    assert!(w.fov().0 < cam.fov().0);
}

#[test]
fn layouts_are_detected() {
    let dir = tempfile::tempdir().unwrap();
    let vs = views();
    // Model directly in the folder: images resolve relative to that folder.
    colmap_txt(&dir.path().join("flat"), &vs);
    let set = load_cameras(&dir.path().join("flat")).unwrap();
    assert_eq!(
        set.image_paths[0],
        Some(dir.path().join("flat/images/a.png"))
    );
    // A model file path selects its folder; sparse/0 maps back to the dataset root.
    colmap_bin(&dir.path().join("ds/sparse/0"), &vs);
    let set = load_cameras(&dir.path().join("ds/sparse/0/images.bin")).unwrap();
    assert_eq!(set.image_paths[0], Some(dir.path().join("ds/images/a.png")));
    let set = load_cameras(&dir.path().join("ds/sparse/0")).unwrap();
    assert_eq!(set.image_paths[0], Some(dir.path().join("ds/images/a.png")));
    // transforms_train.json in a folder; cameras.json in a folder.
    std::fs::create_dir_all(dir.path().join("nerf")).unwrap();
    transforms_json(&dir.path().join("nerf/transforms_train.json"), &vs);
    assert_eq!(
        load_cameras(&dir.path().join("nerf"))
            .unwrap()
            .cameras
            .len(),
        2
    );
    std::fs::create_dir_all(dir.path().join("inria")).unwrap();
    inria_json(&dir.path().join("inria/cameras.json"), &vs);
    assert_eq!(
        load_cameras(&dir.path().join("inria"))
            .unwrap()
            .cameras
            .len(),
        2
    );
    // Existing files with extensions are found for extension-less paths.
    std::fs::create_dir_all(dir.path().join("images")).unwrap();
    std::fs::write(dir.path().join("images/a.jpg"), b"").unwrap();
    let tf = dir.path().join("transforms.json");
    transforms_json(&tf, &vs);
    let set = load_cameras(&tf).unwrap();
    let a = set.cameras.iter().position(|c| c.name == "a").unwrap();
    assert_eq!(set.image_paths[a], Some(dir.path().join("images/a.jpg")));
}

fn lego() -> Option<PathBuf> {
    testkit::paths::shared_asset("lego-200/transforms_train.json")
}

#[test]
fn real_blender_dataset_loads() {
    let Some(path) = lego() else {
        return;
    };
    let set: CameraSet = load_cameras(&path).unwrap();
    assert_eq!(set.cameras.len(), 50);
    let expected_f = 100.0 / (0.5f64 * 0.6911112070083618).tan();
    for (cam, image) in set.cameras.iter().zip(&set.image_paths) {
        assert_eq!((cam.width, cam.height), (200, 200));
        assert!((cam.fx - expected_f).abs() < 1e-9 && cam.fy == cam.fx);
        let image = image.as_ref().unwrap();
        assert!(image.is_file(), "{}", image.display());
        assert_eq!(image.file_stem().unwrap().to_str().unwrap(), cam.name);
        // Blender's cameras orbit the origin at radius ~4 looking at it, upright (z up in the image).
        let c = cam.center();
        let r = (c[0] * c[0] + c[1] * c[1] + c[2] * c[2]).sqrt();
        assert!((r - 4.03).abs() < 0.05, "{r}");
        let o = project(cam, [0.0, 0.0, 0.0]);
        assert!(
            o[2] > 0.0 && (o[0] - 100.0).abs() < 10.0 && (o[1] - 100.0).abs() < 10.0,
            "{o:?}"
        );
        let up = project(cam, [0.0, 0.0, 0.5]);
        assert!(up[1] < o[1], "world +z appears higher in the image");
    }
}

// ---------------------------------------------------------------------------------------------------------
// Malformed inputs

#[test]
fn malformed_camera_files_give_specific_messages() {
    let dir = tempfile::tempdir().unwrap();
    let good_cams = "1 PINHOLE 64 48 50 50 32 24\n";
    let good_imgs = "1 1 0 0 0 0 0 0 1 a.png\n\n";
    let txt_cases: Vec<(&str, &str, &str, &str)> = vec![
        (
            "radial",
            "1 SIMPLE_RADIAL 64 48 50 32 24 0.01\n",
            good_imgs,
            "camera 1 uses the SIMPLE_RADIAL model",
        ),
        (
            "opencv",
            "1 OPENCV 64 48 50 50 32 24 0 0 0 0\n",
            good_imgs,
            "colmap image_undistorter",
        ),
        (
            "params",
            "1 PINHOLE 64 48 50 50 32\n",
            good_imgs,
            "line 1: camera 1 (PINHOLE) has 3 parameters, expected 4",
        ),
        (
            "width",
            "1 PINHOLE 0 48 50 50 32 24\n",
            good_imgs,
            "camera 1: width 0 is not a positive whole number",
        ),
        (
            "focal",
            "1 PINHOLE 64 48 -50 50 32 24\n",
            good_imgs,
            "focal lengths must be positive",
        ),
        (
            "number",
            "1 PINHOLE 64 48 5x0 50 32 24\n",
            good_imgs,
            "line 1: parameter '5x0' is not a number",
        ),
        (
            "short camera line",
            "1 PINHOLE 64\n",
            good_imgs,
            "expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'",
        ),
        (
            "duplicate camera",
            "1 PINHOLE 64 48 50 50 32 24\n1 PINHOLE 64 48 50 50 32 24\n",
            good_imgs,
            "line 2: camera 1 is defined twice",
        ),
        (
            "unknown camera",
            good_cams,
            "1 1 0 0 0 0 0 0 9 a.png\n\n",
            "image 'a.png' refers to camera 9",
        ),
        (
            "zero quaternion",
            good_cams,
            "1 0 0 0 0 0 0 0 1 a.png\n\n",
            "image 'a.png' has a zero or non-finite rotation quaternion",
        ),
        (
            "nan translation",
            good_cams,
            "1 1 0 0 0 nan 0 0 1 a.png\n\n",
            "image 'a.png' has a non-finite translation",
        ),
        (
            "short image line",
            good_cams,
            "1 1 0 0 0 0 0 0 1\n\n",
            "line 1: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'",
        ),
        (
            "bad pose",
            good_cams,
            "1 1 0 0 zero 0 0 0 1 a.png\n\n",
            "line 1: pose value 'zero' is not a number",
        ),
    ];
    for (i, (label, cams, imgs, want)) in txt_cases.into_iter().enumerate() {
        let d = dir.path().join(format!("txt{i}"));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::write(d.join("cameras.txt"), cams).unwrap();
        std::fs::write(d.join("images.txt"), imgs).unwrap();
        let e = load_cameras(&d).unwrap_err().to_string();
        assert!(e.contains(want), "{label}: wanted '{want}' in: {e}");
        assert!(
            e.contains(&d.display().to_string()) && !e.contains('\n'),
            "{label}: {e}"
        );
    }

    // Binary: an OPENCV camera, an unknown model id, a truncated file, trailing bytes, bad points.
    let d = dir.path().join("bin");
    colmap_bin(&d, &views());
    let cams = std::fs::read(d.join("cameras.bin")).unwrap();
    let set_model = |id: i32| {
        let mut c = cams.clone();
        c[12..16].copy_from_slice(&id.to_le_bytes());
        c
    };
    let bin_cases: Vec<(&str, &str, Vec<u8>, &str)> = vec![
        (
            "opencv",
            "cameras.bin",
            set_model(4),
            "uses the OPENCV model",
        ),
        (
            "unknown id",
            "cameras.bin",
            set_model(99),
            "unknown model id 99",
        ),
        (
            "truncated",
            "cameras.bin",
            cams[..cams.len() - 5].to_vec(),
            "the file ends inside camera record 1",
        ),
        (
            "trailing",
            "cameras.bin",
            [cams.as_slice(), &[1, 2, 3]].concat(),
            "3 unexpected bytes after the last record",
        ),
        (
            "huge count",
            "images.bin",
            [u64::MAX.to_le_bytes().as_slice(), &[0; 100]].concat(),
            "declares 18446744073709551615 images",
        ),
        (
            "no name end",
            "images.bin",
            [1u64.to_le_bytes().as_slice(), &[1; 80]].concat(),
            "ends inside the name of image record 0",
        ),
        (
            "points",
            "points3D.bin",
            [1u64.to_le_bytes().as_slice(), &[0; 20]].concat(),
            "declares 1 points",
        ),
    ];
    for (label, file, bytes, want) in bin_cases {
        let d = dir.path().join(format!("bin-{label}"));
        colmap_bin(&d, &views());
        std::fs::write(d.join(file), bytes).unwrap();
        let e = load_cameras(&d).unwrap_err().to_string();
        assert!(
            e.contains(want) && e.contains(file),
            "{label}: wanted '{want}' in: {e}"
        );
    }

    // JSON sources.
    let json_cases = [
        (
            "transforms.json",
            "{\"frames\": [",
            "not a valid transforms.json",
        ),
        (
            "transforms.json",
            "{\"fl_x\": 10, \"w\": 4, \"h\": 4, \"frames\": [{\"file_path\": \"x\"}]}",
            "missing field `transform_matrix`",
        ),
        (
            "cameras.json",
            "[{\"img_name\": \"a\"}]",
            "not a valid INRIA cameras.json",
        ),
        // Named cameras.json, it is read as INRIA's (not sniffed by content), and said to be broken as such.
        ("cameras.json", "   ", "not a valid INRIA cameras.json"),
        ("views.json", "   ", "neither a transforms.json"),
    ];
    for (name, text, want) in json_cases {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        let e = load_cameras(&p).unwrap_err().to_string();
        assert!(
            e.contains(want) && e.contains(name),
            "wanted '{want}' in: {e}"
        );
    }
}

// ---------------------------------------------------------------------------------------------------------
// Fuzzing

fn corrupt(bytes: &mut [u8], edits: &[(prop::sample::Index, u8)]) {
    if bytes.is_empty() {
        return;
    }
    for (at, b) in edits {
        let i = at.index(bytes.len());
        bytes[i] = *b;
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 200, ..ProptestConfig::default() })]

    #[test]
    fn corrupted_colmap_models_never_panic(
        file in 0usize..6,
        edits in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
    ) {
        let dir = tempfile::tempdir().unwrap();
        colmap_txt(&dir.path().join("t"), &views());
        colmap_bin(&dir.path().join("b"), &views());
        let target = [
            "t/cameras.txt", "t/images.txt", "t/points3D.txt", "b/cameras.bin", "b/images.bin", "b/points3D.bin",
        ][file];
        let p = dir.path().join(target);
        let mut bytes = std::fs::read(&p).unwrap();
        corrupt(&mut bytes, &edits);
        std::fs::write(&p, &bytes).unwrap();
        let model = p.parent().unwrap();
        if let Err(e) = load_cameras(model) {
            prop_assert!(!e.to_string().contains('\n'));
        }
    }

    #[test]
    fn truncated_colmap_binaries_are_errors(file in 0usize..3, cut in any::<prop::sample::Index>()) {
        let dir = tempfile::tempdir().unwrap();
        colmap_bin(dir.path(), &views());
        let p = dir.path().join(["cameras.bin", "images.bin", "points3D.bin"][file]);
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..cut.index(bytes.len())]).unwrap();
        prop_assert!(load_cameras(dir.path()).is_err());
    }

    #[test]
    fn corrupted_json_never_panics(
        inria in any::<bool>(),
        edits in prop::collection::vec((any::<prop::sample::Index>(), prop::sample::select(b"0123456789.-e,[]{}\": nul".to_vec())), 1..6),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join(if inria { "cameras.json" } else { "transforms.json" });
        if inria { inria_json(&p, &views()) } else { transforms_json(&p, &views()) }
        let mut bytes = std::fs::read(&p).unwrap();
        corrupt(&mut bytes, &edits);
        std::fs::write(&p, &bytes).unwrap();
        if let Ok(set) = load_cameras(&p) {
            // Whatever parses must be usable: finite poses, positive focal lengths.
            for c in &set.cameras {
                prop_assert!(c.fx > 0.0 && c.fy > 0.0 && c.width > 0 && c.height > 0);
                prop_assert!(c.rotation.iter().flatten().chain(&c.translation).all(|v| v.is_finite()));
            }
        }
    }
}
