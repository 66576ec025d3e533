//! The in-memory 3DGS scene: structure-of-arrays, parameters in their raw (trainable) form.

/// Number of SH coefficients per colour channel for a degree.
pub const fn sh_coeffs(degree: u32) -> usize {
    ((degree + 1) * (degree + 1)) as usize
}

/// A set of 3D Gaussians, stored as the INRIA trainer stores them.
///
/// All vectors have one entry per Gaussian (`len()`), flattened:
/// - `means[3n..3n+3]`: world position.
/// - `log_scales[3n..3n+3]`: natural log of the per-axis standard deviation.
/// - `quats[4n..4n+4]`: rotation quaternion (w, x, y, z), not necessarily normalised.
/// - `opacity_logits[n]`: logit of the opacity.
/// - `sh[(n*K + k)*3 + c]`: SH coefficient k (0 = DC) of colour channel c, K = `sh_coeffs(sh_degree)`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct GaussianScene {
    pub sh_degree: u32,
    pub means: Vec<f32>,
    pub log_scales: Vec<f32>,
    pub quats: Vec<f32>,
    pub opacity_logits: Vec<f32>,
    pub sh: Vec<f32>,
}

impl GaussianScene {
    /// An empty scene with the given SH degree.
    pub fn new(sh_degree: u32) -> Self {
        Self {
            sh_degree,
            ..Default::default()
        }
    }

    /// An empty scene with the given SH degree and room for `n` Gaussians (a reader that knows its count).
    pub fn with_capacity(sh_degree: u32, n: usize) -> Self {
        Self {
            sh_degree,
            means: Vec::with_capacity(3 * n),
            log_scales: Vec::with_capacity(3 * n),
            quats: Vec::with_capacity(4 * n),
            opacity_logits: Vec::with_capacity(n),
            sh: Vec::with_capacity(3 * sh_coeffs(sh_degree) * n),
        }
    }

    pub fn len(&self) -> usize {
        self.opacity_logits.len()
    }

    pub fn is_empty(&self) -> bool {
        self.opacity_logits.is_empty()
    }

    /// SH coefficients per colour channel.
    pub fn sh_coeffs(&self) -> usize {
        sh_coeffs(self.sh_degree)
    }

    /// Bytes the parameters of `n` Gaussians of SH degree `sh_degree` take in memory.
    pub fn memory_bytes(n: u64, sh_degree: u32) -> u64 {
        n.saturating_mul((11 + 3 * sh_coeffs(sh_degree) as u64) * 4)
    }

    /// Checks that every array has the length `len()` implies. Returns a description of the first problem.
    pub fn check_shapes(&self) -> Result<(), String> {
        let n = self.len();
        let k = self.sh_coeffs();
        let checks = [
            ("means", self.means.len(), 3 * n),
            ("log_scales", self.log_scales.len(), 3 * n),
            ("quats", self.quats.len(), 4 * n),
            ("sh", self.sh.len(), 3 * k * n),
        ];
        for (name, got, want) in checks {
            if got != want {
                return Err(format!(
                    "{name} has {got} values, expected {want} for {n} Gaussians"
                ));
            }
        }
        Ok(())
    }

    /// Checks that every Gaussian decodes to finite values: finite positions, SH coefficients and opacity
    /// logits, log-scales whose scale `exp(s)` is a finite f32 (a log-scale of 1e30 is finite but its
    /// scale is not), and quaternions that can be normalised. Returns the first problem, naming the
    /// Gaussian. Readers call it on every scene they decode: a value that overflows would otherwise pass
    /// `inspect` and `render` and fail much later, or render garbage.
    pub fn check_values(&self) -> Result<(), String> {
        self.check_shapes()?;
        let k = 3 * self.sh_coeffs();
        for i in 0..self.len() {
            let bad = |what: &str, values: &[f32]| Err(format!("Gaussian {i}: {what} {values:?}"));
            let mean = &self.means[3 * i..3 * i + 3];
            if !mean.iter().all(|v| v.is_finite()) {
                return bad("position is not finite:", mean);
            }
            let log_scale = &self.log_scales[3 * i..3 * i + 3];
            if !log_scale
                .iter()
                .all(|v| v.is_finite() && v.exp().is_finite())
            {
                return bad("log-scales give no finite scale:", log_scale);
            }
            let q = &self.quats[4 * i..4 * i + 4];
            let norm2: f32 = q.iter().map(|v| v * v).sum();
            if !(norm2.is_finite() && norm2 > 0.0) {
                return bad("rotation quaternion cannot be normalised:", q);
            }
            let logit = self.opacity_logits[i];
            if !logit.is_finite() {
                return bad("opacity logit is not finite:", &[logit]);
            }
            let sh = &self.sh[k * i..k * i + k];
            if !sh.iter().all(|v| v.is_finite()) {
                return bad("colour (SH) coefficients are not finite:", sh);
            }
        }
        Ok(())
    }

    /// Position of Gaussian `i`.
    pub fn mean(&self, i: usize) -> [f32; 3] {
        [
            self.means[3 * i],
            self.means[3 * i + 1],
            self.means[3 * i + 2],
        ]
    }

    /// Opacity in (0, 1) of Gaussian `i`.
    pub fn opacity(&self, i: usize) -> f32 {
        1.0 / (1.0 + (-self.opacity_logits[i]).exp())
    }

    /// Per-axis standard deviations of Gaussian `i`.
    pub fn scale(&self, i: usize) -> [f32; 3] {
        let s = &self.log_scales[3 * i..3 * i + 3];
        [s[0].exp(), s[1].exp(), s[2].exp()]
    }

    /// Axis-aligned bounds of the means: (min, max). `None` for an empty scene.
    pub fn bounds(&self) -> Option<([f32; 3], [f32; 3])> {
        if self.is_empty() {
            return None;
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        for p in self.means.chunks_exact(3) {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
        Some((lo, hi))
    }

    /// Keeps the Gaussians whose `keep` flag is set, preserving order.
    pub fn retain(&mut self, keep: &[bool]) {
        assert_eq!(keep.len(), self.len());
        let k3 = 3 * self.sh_coeffs();
        fn filter(v: &mut Vec<f32>, width: usize, keep: &[bool]) {
            let mut w = 0;
            for (i, &kp) in keep.iter().enumerate() {
                if kp {
                    v.copy_within(i * width..(i + 1) * width, w * width);
                    w += 1;
                }
            }
            v.truncate(w * width);
        }
        filter(&mut self.means, 3, keep);
        filter(&mut self.log_scales, 3, keep);
        filter(&mut self.quats, 4, keep);
        filter(&mut self.opacity_logits, 1, keep);
        filter(&mut self.sh, k3, keep);
    }

    /// Appends all Gaussians of `other` (same SH degree).
    pub fn extend_from(&mut self, other: &GaussianScene) {
        assert_eq!(self.sh_degree, other.sh_degree);
        self.means.extend_from_slice(&other.means);
        self.log_scales.extend_from_slice(&other.log_scales);
        self.quats.extend_from_slice(&other.quats);
        self.opacity_logits.extend_from_slice(&other.opacity_logits);
        self.sh.extend_from_slice(&other.sh);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn two() -> GaussianScene {
        GaussianScene {
            sh_degree: 0,
            means: vec![0.0, 1.0, 2.0, 3.0, 4.0, 5.0],
            log_scales: vec![0.0; 6],
            quats: vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
            opacity_logits: vec![0.0, 1.0],
            sh: vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6],
        }
    }

    #[test]
    fn retain_keeps_selected_in_order() {
        let mut s = two();
        s.retain(&[false, true]);
        assert_eq!(s.len(), 1);
        assert_eq!(s.means, vec![3.0, 4.0, 5.0]);
        assert_eq!(s.sh, vec![0.4, 0.5, 0.6]);
        assert!(s.check_shapes().is_ok());
    }

    #[test]
    fn bounds_and_opacity() {
        let s = two();
        assert_eq!(s.bounds(), Some(([0.0, 1.0, 2.0], [3.0, 4.0, 5.0])));
        assert!((s.opacity(0) - 0.5).abs() < 1e-7);
    }
}
