//! antimatter15's `.splat`: no header, 32 bytes per Gaussian, little-endian:
//!
//! | bytes | content |
//! | --- | --- |
//! | 0..12 | position, 3 × f32 |
//! | 12..24 | scale (standard deviations, linear), 3 × f32 |
//! | 24..28 | colour 0.5 + C0 · DC and opacity, 4 × u8 (value · 255, rounded, clamped) |
//! | 28..32 | rotation (w, x, y, z), unit and w ≥ 0, 4 × u8 (value · 128 + 128) |
//!
//! Only the DC colour is stored (higher SH bands are dropped), and colours outside [0, 1] are clamped.
//! Reading keeps the file's order; readers and writers never depend on it.

use super::codec::{check_quats, logit, to_byte, unit_quat, SH_C0};
use crate::scene::GaussianScene;

/// Bytes per Gaussian.
pub const RECORD_BYTES: usize = 32;

/// Packs Gaussian `i` of `scene` into one record.
pub fn encode_record(scene: &GaussianScene, i: usize) -> [u8; RECORD_BYTES] {
    let mut out = [0u8; RECORD_BYTES];
    let scale = scene.scale(i).map(|s| s.max(f32::MIN_POSITIVE));
    for (k, v) in scene.mean(i).into_iter().chain(scale).enumerate() {
        out[4 * k..4 * k + 4].copy_from_slice(&v.to_le_bytes());
    }
    let dc = &scene.sh[i * 3 * scene.sh_coeffs()..][..3];
    for c in 0..3 {
        out[24 + c] = to_byte(0.5 + SH_C0 * dc[c]);
    }
    out[27] = to_byte(scene.opacity(i));
    let q = unit_quat(&scene.quats, i);
    // q and -q are the same rotation; w ≥ 0 makes the record unique.
    let sign = if q[0] < 0.0 { -1.0 } else { 1.0 };
    for (k, v) in q.iter().enumerate() {
        out[28 + k] = (sign * v * 128.0 + 128.0).round().clamp(0.0, 255.0) as u8;
    }
    out
}

/// Encodes a whole scene.
pub fn encode(scene: &GaussianScene) -> Result<Vec<u8>, String> {
    check_quats(scene)?;
    let mut out = Vec::with_capacity(scene.len() * RECORD_BYTES);
    for i in 0..scene.len() {
        out.extend_from_slice(&encode_record(scene, i));
    }
    Ok(out)
}

/// Decodes a `.splat` file's bytes (SH degree 0).
pub fn decode(bytes: &[u8]) -> Result<GaussianScene, String> {
    if bytes.is_empty() || !bytes.len().is_multiple_of(RECORD_BYTES) {
        return Err(format!(
            "a .splat file holds {RECORD_BYTES} bytes per Gaussian, but this one has {} bytes",
            bytes.len()
        ));
    }
    let n = bytes.len() / RECORD_BYTES;
    let mut scene = GaussianScene::new(0);
    scene.means.reserve(3 * n);
    scene.log_scales.reserve(3 * n);
    scene.quats.reserve(4 * n);
    scene.opacity_logits.reserve(n);
    scene.sh.reserve(3 * n);
    for (i, rec) in bytes.chunks_exact(RECORD_BYTES).enumerate() {
        let f = |k: usize| f32::from_le_bytes(rec[4 * k..4 * k + 4].try_into().expect("4 bytes"));
        for k in 0..3 {
            let p = f(k);
            if !p.is_finite() {
                return Err(format!("Gaussian {i}: position is {p}"));
            }
            scene.means.push(p);
        }
        for k in 3..6 {
            let s = f(k);
            if !(s.is_finite() && s > 0.0) {
                return Err(format!(
                    "Gaussian {i}: scale is {s} (must be positive and finite)"
                ));
            }
            scene.log_scales.push(s.ln());
        }
        for c in 0..3 {
            scene
                .sh
                .push((f32::from(rec[24 + c]) / 255.0 - 0.5) / SH_C0);
        }
        scene.opacity_logits.push(logit(f32::from(rec[27]) / 255.0));
        let q: [f32; 4] = std::array::from_fn(|k| (f32::from(rec[28 + k]) - 128.0) / 128.0);
        let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
        if norm == 0.0 {
            return Err(format!("Gaussian {i}: the rotation is the zero quaternion"));
        }
        scene.quats.extend(q.iter().map(|v| v / norm));
    }
    Ok(scene)
}
