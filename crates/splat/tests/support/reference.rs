//! Test support for the renderer reference fixtures (fixtures/render, made by
//! tools/make_render_fixtures.py): a tiny safetensors reader and the camera JSON format.
//! Shared by the unit tests (via `#[path]`) and the integration tests.

use super::{Camera, GaussianScene};
use std::collections::HashMap;
use std::path::{Path, PathBuf};

/// The repository's fixtures/render directory.
pub fn fixture_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../fixtures/render")
}

/// The shared assets directory beside the repository (absent in a user's clone).
pub fn assets_dir() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/assets")
}

pub fn manifest() -> serde_json::Value {
    let path = fixture_dir().join("reference.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// All tensors of one safetensors file, converted to f64 on access.
pub struct Tensors {
    header: HashMap<String, serde_json::Value>,
    data: Vec<u8>,
}

impl Tensors {
    pub fn load(path: &Path) -> Self {
        let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
        let header: HashMap<String, serde_json::Value> =
            serde_json::from_slice(&bytes[8..8 + n]).expect("safetensors header");
        Self {
            header,
            data: bytes[8 + n..].to_vec(),
        }
    }

    /// The fixture's scene (its `scene.*` tensors), with SH degree `sh_degree`.
    pub fn scene(&self, sh_degree: u32) -> GaussianScene {
        GaussianScene {
            sh_degree,
            means: self.f32("scene.means"),
            log_scales: self.f32("scene.log_scales"),
            quats: self.f32("scene.quats"),
            opacity_logits: self.f32("scene.opacity_logits"),
            sh: self.f32("scene.sh"),
        }
    }

    pub fn shape(&self, name: &str) -> Vec<usize> {
        let t = self
            .header
            .get(name)
            .unwrap_or_else(|| panic!("no tensor {name}"));
        t["shape"]
            .as_array()
            .unwrap()
            .iter()
            .map(|v| v.as_u64().unwrap() as usize)
            .collect()
    }

    pub fn f64(&self, name: &str) -> Vec<f64> {
        let t = self
            .header
            .get(name)
            .unwrap_or_else(|| panic!("no tensor {name}"));
        let off = t["data_offsets"].as_array().unwrap();
        let (a, b) = (
            off[0].as_u64().unwrap() as usize,
            off[1].as_u64().unwrap() as usize,
        );
        let raw = &self.data[a..b];
        match t["dtype"].as_str().unwrap() {
            "F64" => raw
                .chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
                .collect(),
            "F32" => raw
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes(c.try_into().unwrap()) as f64)
                .collect(),
            "F16" => raw
                .chunks_exact(2)
                .map(|c| f16_to_f64(u16::from_le_bytes([c[0], c[1]])))
                .collect(),
            d => panic!("unsupported dtype {d}"),
        }
    }

    pub fn f32(&self, name: &str) -> Vec<f32> {
        self.f64(name).into_iter().map(|v| v as f32).collect()
    }
}

fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    match exp {
        0 => sign * frac * 2f64.powi(-24),
        31 => {
            if frac == 0.0 {
                sign * f64::INFINITY
            } else {
                f64::NAN
            }
        }
        e => sign * (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

pub fn camera_from_json(v: &serde_json::Value) -> Camera {
    let f = |k: &str| v[k].as_f64().unwrap_or_else(|| panic!("camera field {k}"));
    let m = |k: &str| -> Vec<f64> {
        let mut out = vec![];
        let a = v[k].as_array().unwrap();
        for e in a {
            match e.as_array() {
                Some(row) => out.extend(row.iter().map(|x| x.as_f64().unwrap())),
                None => out.push(e.as_f64().unwrap()),
            }
        }
        out
    };
    let r = m("rotation");
    let t = m("translation");
    Camera {
        name: v["name"].as_str().unwrap_or("view").to_string(),
        width: v["width"].as_u64().unwrap() as u32,
        height: v["height"].as_u64().unwrap() as u32,
        fx: f("fx"),
        fy: f("fy"),
        cx: f("cx"),
        cy: f("cy"),
        rotation: [[r[0], r[1], r[2]], [r[3], r[4], r[5]], [r[6], r[7], r[8]]],
        translation: [t[0], t[1], t[2]],
    }
}

pub fn background(v: &serde_json::Value) -> [f32; 3] {
    background_f64(v).map(|x| x as f32)
}

pub fn background_f64(v: &serde_json::Value) -> [f64; 3] {
    let a = v.as_array().unwrap();
    [0, 1, 2].map(|i| a[i].as_f64().unwrap())
}

/// Peak signal-to-noise ratio for signals in [0, 1].
pub fn psnr(a: &[f32], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let mse = a
        .iter()
        .zip(b)
        .map(|(&x, &y)| (x as f64 - y).powi(2))
        .sum::<f64>()
        / a.len() as f64;
    -10.0 * mse.log10()
}

/// ‖a − b‖ / ‖b‖.
pub fn relative_error(a: &[f64], b: &[f64]) -> f64 {
    assert_eq!(a.len(), b.len());
    let num: f64 = a.iter().zip(b).map(|(x, y)| (x - y).powi(2)).sum();
    let den: f64 = b.iter().map(|y| y * y).sum();
    (num / den.max(1e-300)).sqrt()
}
