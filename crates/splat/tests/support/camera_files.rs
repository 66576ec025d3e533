//! Camera files of every supported kind written from the same test views: the seeds of the camera
//! loaders' tests (`cameras_io.rs`) and of their fuzzing (`fuzz_readers.rs`).
#![allow(dead_code)]

use std::fmt::Write as _;
use std::path::Path;

/// A test pose: camera-to-world rotation (OpenCV axes) from a quaternion, and a centre.
#[derive(Clone, Copy)]
pub struct Pose {
    pub q: [f64; 4],
    pub center: [f64; 3],
}

pub fn quat_matrix(q: [f64; 4]) -> [[f64; 3]; 3] {
    // Through glam: independent of the loaders' own conversion.
    let [w, x, y, z] = q;
    let m = glam::DMat3::from_quat(glam::DQuat::from_xyzw(x, y, z, w).normalize());
    m.transpose().to_cols_array_2d()
}

impl Pose {
    pub fn c2w(&self) -> [[f64; 3]; 3] {
        quat_matrix(self.q)
    }
    /// COLMAP's world-to-camera quaternion (the conjugate) and translation -R C.
    pub fn colmap(&self) -> ([f64; 4], [f64; 3]) {
        let n = self.q.iter().map(|v| v * v).sum::<f64>().sqrt();
        let [w, x, y, z] = self.q.map(|v| v / n);
        let r = self.c2w();
        let t = std::array::from_fn(|i| -(0..3).map(|k| r[k][i] * self.center[k]).sum::<f64>());
        ([w, -x, -y, -z], t)
    }
}

pub struct View {
    pub name: &'static str,
    pub width: u32,
    pub height: u32,
    pub fx: f64,
    pub fy: f64,
    pub cx: f64,
    pub cy: f64,
    pub pose: Pose,
}

pub fn views() -> Vec<View> {
    vec![
        View {
            name: "b.png",
            width: 640,
            height: 480,
            fx: 500.0,
            fy: 510.0,
            cx: 321.5,
            cy: 239.25,
            pose: Pose {
                q: [0.8, 0.1, -0.4, 0.3],
                center: [1.0, -2.0, 3.5],
            },
        },
        View {
            name: "a.png",
            width: 300,
            height: 200,
            fx: 280.0,
            fy: 280.0,
            cx: 150.0,
            cy: 100.0,
            pose: Pose {
                q: [-0.2, 0.7, 0.1, 0.6],
                center: [-0.5, 0.25, -4.0],
            },
        },
    ]
}

pub fn colmap_txt(dir: &Path, views: &[View]) {
    std::fs::create_dir_all(dir).unwrap();
    let mut cams = "# Camera list with one line of data per camera:\n".to_string();
    let mut imgs = "# Image list with two lines of data per image:\n".to_string();
    for (i, v) in views.iter().enumerate() {
        let id = i + 1;
        if v.fx == v.fy {
            writeln!(
                cams,
                "{id} SIMPLE_PINHOLE {} {} {} {} {}",
                v.width, v.height, v.fx, v.cx, v.cy
            )
            .unwrap();
        } else {
            writeln!(
                cams,
                "{id} PINHOLE {} {} {} {} {} {}",
                v.width, v.height, v.fx, v.fy, v.cx, v.cy
            )
            .unwrap();
        }
        let (q, t) = v.pose.colmap();
        writeln!(
            imgs,
            "{id} {} {} {} {} {} {} {} {id} {}\n{}",
            q[0],
            q[1],
            q[2],
            q[3],
            t[0],
            t[1],
            t[2],
            v.name,
            if i == 0 { "10.5 20.5 -1 30 40 1" } else { "" }
        )
        .unwrap();
    }
    std::fs::write(dir.join("cameras.txt"), cams).unwrap();
    std::fs::write(dir.join("images.txt"), imgs).unwrap();
    std::fs::write(
        dir.join("points3D.txt"),
        "# 3D point list\n1 0.5 -1 2 255 0 51 0.1 1 0 2 1\n7 1e-3 2 -3 0 128 255 0.4 1 1\n",
    )
    .unwrap();
}

pub fn colmap_bin(dir: &Path, views: &[View]) {
    std::fs::create_dir_all(dir).unwrap();
    let mut cams = (views.len() as u64).to_le_bytes().to_vec();
    let mut imgs = (views.len() as u64).to_le_bytes().to_vec();
    for (i, v) in views.iter().enumerate() {
        let id = i as i32 + 1;
        cams.extend_from_slice(&id.to_le_bytes());
        let params: Vec<f64> = if v.fx == v.fy {
            cams.extend_from_slice(&0i32.to_le_bytes());
            vec![v.fx, v.cx, v.cy]
        } else {
            cams.extend_from_slice(&1i32.to_le_bytes());
            vec![v.fx, v.fy, v.cx, v.cy]
        };
        cams.extend_from_slice(&(v.width as u64).to_le_bytes());
        cams.extend_from_slice(&(v.height as u64).to_le_bytes());
        params
            .iter()
            .for_each(|p| cams.extend_from_slice(&p.to_le_bytes()));

        let (q, t) = v.pose.colmap();
        imgs.extend_from_slice(&id.to_le_bytes());
        q.iter()
            .chain(&t)
            .for_each(|x| imgs.extend_from_slice(&x.to_le_bytes()));
        imgs.extend_from_slice(&id.to_le_bytes());
        imgs.extend_from_slice(v.name.as_bytes());
        imgs.push(0);
        let points: &[(f64, f64, i64)] = if i == 0 {
            &[(10.5, 20.5, -1), (30.0, 40.0, 1)]
        } else {
            &[]
        };
        imgs.extend_from_slice(&(points.len() as u64).to_le_bytes());
        for (x, y, pid) in points {
            imgs.extend_from_slice(&x.to_le_bytes());
            imgs.extend_from_slice(&y.to_le_bytes());
            imgs.extend_from_slice(&pid.to_le_bytes());
        }
    }
    let mut pts = 2u64.to_le_bytes().to_vec();
    for (id, xyz, rgb, track) in [
        (
            1u64,
            [0.5, -1.0, 2.0],
            [255u8, 0, 51],
            vec![(0i32, 2i32), (1, 0)],
        ),
        (7, [1e-3, 2.0, -3.0], [0, 128, 255], vec![(1, 1)]),
    ] {
        pts.extend_from_slice(&id.to_le_bytes());
        xyz.iter()
            .for_each(|v: &f64| pts.extend_from_slice(&v.to_le_bytes()));
        pts.extend_from_slice(&rgb);
        pts.extend_from_slice(&0.25f64.to_le_bytes());
        pts.extend_from_slice(&(track.len() as u64).to_le_bytes());
        for (a, b) in track {
            pts.extend_from_slice(&a.to_le_bytes());
            pts.extend_from_slice(&b.to_le_bytes());
        }
    }
    std::fs::write(dir.join("cameras.bin"), cams).unwrap();
    std::fs::write(dir.join("images.bin"), imgs).unwrap();
    std::fs::write(dir.join("points3D.bin"), pts).unwrap();
}

pub fn transforms_json(path: &Path, views: &[View]) {
    let frames: Vec<serde_json::Value> = views
        .iter()
        .map(|v| {
            let r = v.pose.c2w();
            // OpenCV -> OpenGL: negate the camera's y and z axes (columns 1 and 2).
            let m: Vec<Vec<f64>> = (0..3)
                .map(|i| vec![r[i][0], -r[i][1], -r[i][2], v.pose.center[i]])
                .chain([vec![0.0, 0.0, 0.0, 1.0]])
                .collect();
            serde_json::json!({
                "file_path": format!("images/{}", v.name.trim_end_matches(".png")),
                "transform_matrix": m,
                "fl_x": v.fx, "fl_y": v.fy, "cx": v.cx, "cy": v.cy, "w": v.width, "h": v.height,
            })
        })
        .collect();
    let json = serde_json::json!({ "camera_model": "OPENCV", "k1": 0.0, "frames": frames });
    std::fs::write(path, serde_json::to_string_pretty(&json).unwrap()).unwrap();
}

pub fn inria_json(path: &Path, views: &[View]) {
    let list: Vec<serde_json::Value> = views
        .iter()
        .enumerate()
        .map(|(i, v)| {
            serde_json::json!({
                "id": i, "img_name": v.name.trim_end_matches(".png"), "width": v.width, "height": v.height,
                "position": v.pose.center, "rotation": v.pose.c2w(), "fx": v.fx, "fy": v.fy,
            })
        })
        .collect();
    std::fs::write(path, serde_json::to_string(&list).unwrap()).unwrap();
}
