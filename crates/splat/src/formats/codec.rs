//! Small pieces every format shares: activations, quantisation and bounds-checked byte reading.

/// The zeroth-order SH basis constant: colour = 0.5 + C0 · DC coefficient.
pub(crate) const SH_C0: f32 = 0.282_094_8;

/// Quantised opacities are clamped this far from 0 and 1 before the logit, so 0 and 255 stay finite.
const OPACITY_EPS: f32 = 1e-6;

pub(crate) fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// The logit of an opacity in [0, 1], clamped to stay finite.
pub(crate) fn logit(p: f32) -> f32 {
    let p = p.clamp(OPACITY_EPS, 1.0 - OPACITY_EPS);
    (p / (1.0 - p)).ln()
}

/// `v` in [0, 1] rounded onto `bits` bits.
pub(crate) fn pack_unorm(v: f32, bits: u32) -> u32 {
    let top = ((1u32 << bits) - 1) as f32;
    (v * top + 0.5).floor().clamp(0.0, top) as u32
}

pub(crate) fn unpack_unorm(v: u32, bits: u32) -> f32 {
    let top = (1u32 << bits) - 1;
    (v & top) as f32 / top as f32
}

/// A value in [0, 1] rounded to a byte.
pub(crate) fn to_byte(v: f32) -> u8 {
    (v * 255.0).round().clamp(0.0, 255.0) as u8
}

/// Quaternion `i` of a scene, normalised, (w, x, y, z). Writers check first that no quaternion is zero.
pub(crate) fn unit_quat(quats: &[f32], i: usize) -> [f32; 4] {
    let q = &quats[4 * i..4 * i + 4];
    let norm = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    if norm > 0.0 && norm.is_finite() {
        [q[0] / norm, q[1] / norm, q[2] / norm, q[3] / norm]
    } else {
        [1.0, 0.0, 0.0, 0.0]
    }
}

/// The index of the largest-magnitude component (the first one on ties).
pub(crate) fn largest_component(q: &[f32; 4]) -> usize {
    (1..4).fold(
        0,
        |best, i| if q[i].abs() > q[best].abs() { i } else { best },
    )
}

/// Checks that every quaternion can be normalised; lossy writers need a direction.
pub(crate) fn check_quats(scene: &crate::scene::GaussianScene) -> Result<(), String> {
    for (i, q) in scene.quats.chunks_exact(4).enumerate() {
        let norm2: f32 = q.iter().map(|v| v * v).sum();
        if !norm2.is_normal() {
            return Err(format!(
                "Gaussian {i} has a zero rotation quaternion ({}, {}, {}, {})",
                q[0], q[1], q[2], q[3]
            ));
        }
    }
    Ok(())
}

/// A bounds-checked little-endian reader over bytes: every read says what was being read when it fails.
pub(crate) struct Bytes<'a> {
    data: &'a [u8],
    pos: usize,
}

impl<'a> Bytes<'a> {
    pub(crate) fn new(data: &'a [u8]) -> Self {
        Self { data, pos: 0 }
    }

    pub(crate) fn remaining(&self) -> usize {
        self.data.len() - self.pos
    }

    pub(crate) fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], String> {
        if n > self.remaining() {
            return Err(format!(
                "the data ends inside {what}: {n} bytes needed at offset {}, {} left (truncated?)",
                self.pos,
                self.remaining()
            ));
        }
        let out = &self.data[self.pos..self.pos + n];
        self.pos += n;
        Ok(out)
    }

    pub(crate) fn u8(&mut self, what: &str) -> Result<u8, String> {
        Ok(self.take(1, what)?[0])
    }

    pub(crate) fn u32(&mut self, what: &str) -> Result<u32, String> {
        Ok(u32::from_le_bytes(
            self.take(4, what)?.try_into().expect("4 bytes"),
        ))
    }

    pub(crate) fn u64(&mut self, what: &str) -> Result<u64, String> {
        Ok(u64::from_le_bytes(
            self.take(8, what)?.try_into().expect("8 bytes"),
        ))
    }
}

/// `count * per_item` as a byte count, refusing overflow.
pub(crate) fn size_of(count: u64, per_item: u64, what: &str) -> Result<usize, String> {
    count
        .checked_mul(per_item)
        .and_then(|b| usize::try_from(b).ok())
        .ok_or_else(|| format!("{count} {what} need more bytes than this machine can address"))
}
