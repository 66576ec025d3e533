//! What a write did to a scene: exact, or the largest error of each quantity.

use super::codec::{sigmoid, unit_quat, SH_C0};
use super::OutputFormat;
use crate::scene::GaussianScene;
use std::fmt;

/// The largest error of each quantity between a scene and what a reader gets back from the file written.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct QuantisationError {
    /// Largest absolute error of a position coordinate (scene units).
    pub position: f32,
    /// Largest absolute error of a log-scale (natural log of the standard deviation).
    pub log_scale: f32,
    /// Largest angle between a rotation and its stored version, in degrees.
    pub rotation_deg: f32,
    /// Largest absolute error of an opacity in [0, 1] (after the sigmoid).
    pub opacity: f32,
    /// Largest absolute error of a base (DC) colour channel in [0, 1] units: C0 · |ΔDC|.
    pub colour: f32,
    /// Largest absolute error of a higher-order SH coefficient; coefficients of bands the format drops
    /// count with their whole value.
    pub sh_rest: f32,
}

/// The outcome of [`super::write_scene`].
#[derive(Clone, Debug, PartialEq)]
pub struct WriteReport {
    pub format: OutputFormat,
    pub gaussians: usize,
    /// The SH degree of the scene given.
    pub sh_degree: u32,
    /// The SH degree stored in the file (lower where the format cannot hold the scene's).
    pub written_sh_degree: u32,
    /// Bytes written (all files of a SOG folder together).
    pub bytes: u64,
    /// `None` for an exact write.
    pub error: Option<QuantisationError>,
}

impl WriteReport {
    pub(crate) fn lossless(format: OutputFormat, scene: &GaussianScene, bytes: u64) -> Self {
        Self {
            format,
            gaussians: scene.len(),
            sh_degree: scene.sh_degree,
            written_sh_degree: scene.sh_degree,
            bytes,
            error: None,
        }
    }

    /// Compares `scene` with `decoded` (the file's content as a reader sees it, in the same order).
    pub(crate) fn measured(
        format: OutputFormat,
        scene: &GaussianScene,
        decoded: &GaussianScene,
        bytes: u64,
    ) -> Self {
        Self {
            format,
            gaussians: scene.len(),
            sh_degree: scene.sh_degree,
            written_sh_degree: decoded.sh_degree,
            bytes,
            error: Some(QuantisationError::between(scene, decoded)),
        }
    }

    pub fn is_lossless(&self) -> bool {
        self.error.is_none()
    }
}

fn max_abs_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max)
}

impl QuantisationError {
    /// The largest errors of `decoded` against `original` (same Gaussians in the same order).
    pub fn between(original: &GaussianScene, decoded: &GaussianScene) -> Self {
        assert_eq!(
            original.len(),
            decoded.len(),
            "a format changed the number of Gaussians"
        );
        let n = original.len();
        let (ka, kb) = (original.sh_coeffs(), decoded.sh_coeffs());
        let mut colour = 0.0f32;
        let mut sh_rest = 0.0f32;
        let mut opacity = 0.0f32;
        let mut rotation_cos = 1.0f32;
        for i in 0..n {
            let a = &original.sh[3 * ka * i..3 * ka * (i + 1)];
            let b = &decoded.sh[3 * kb * i..3 * kb * (i + 1)];
            colour = colour.max(SH_C0 * max_abs_diff(&a[..3], &b[..3]));
            for (k, coeff) in a.iter().enumerate().skip(3) {
                let back = b.get(k).copied().unwrap_or(0.0);
                sh_rest = sh_rest.max((coeff - back).abs());
            }
            opacity = opacity.max(
                (sigmoid(original.opacity_logits[i]) - sigmoid(decoded.opacity_logits[i])).abs(),
            );
            let (qa, qb) = (unit_quat(&original.quats, i), unit_quat(&decoded.quats, i));
            let dot: f32 = qa.iter().zip(&qb).map(|(x, y)| x * y).sum();
            rotation_cos = rotation_cos.min(dot.abs().min(1.0));
        }
        Self {
            position: max_abs_diff(&original.means, &decoded.means),
            log_scale: max_abs_diff(&original.log_scales, &decoded.log_scales),
            rotation_deg: 2.0 * rotation_cos.acos().to_degrees(),
            opacity,
            colour,
            sh_rest,
        }
    }
}

/// A non-negative error for reading: plain decimals from 0.01 up, one significant digit below.
fn short(v: f32) -> String {
    if v == 0.0 {
        "0".into()
    } else if v >= 0.01 {
        format!("{v:.3}")
    } else {
        format!("{v:.1e}")
    }
}

/// A colour error beyond this (in 0–1 units) is not rounding (8-bit steps are 0.002) but clamping.
const CLAMPED_COLOUR: f32 = 0.01;

impl fmt::Display for QuantisationError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "position {} (scene units), log-scale {}, rotation {}°, opacity {}, colour {} (0–1 scale",
            short(self.position),
            short(self.log_scale),
            short(self.rotation_deg),
            short(self.opacity),
            short(self.colour),
        )?;
        if self.colour > CLAMPED_COLOUR {
            write!(f, "; colours outside 0–1 were clamped")?;
        }
        write!(f, "), SH {}", short(self.sh_rest))
    }
}

impl fmt::Display for WriteReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{} Gaussians, SH degree {}",
            self.gaussians, self.written_sh_degree
        )?;
        if self.written_sh_degree < self.sh_degree {
            write!(
                f,
                " ({} cannot hold the scene's degree {})",
                self.format.name(),
                self.sh_degree
            )?;
        }
        write!(f, ", {} bytes, {}", self.bytes, self.format.name())?;
        match &self.error {
            None => write!(f, ", lossless"),
            Some(e) => write!(f, ", lossy: largest error {e}"),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn errors_read_with_units_and_say_when_colours_were_clamped() {
        let rounding = QuantisationError {
            position: 1.234e-4,
            log_scale: 0.0,
            rotation_deg: 0.25,
            opacity: 2e-3,
            colour: 1.9e-3,
            sh_rest: 0.0,
        };
        let text = rounding.to_string();
        assert_eq!(
            text,
            "position 1.2e-4 (scene units), log-scale 0, rotation 0.250°, opacity 2.0e-3, \
             colour 1.9e-3 (0–1 scale), SH 0"
        );
        let clamped = QuantisationError {
            colour: 2.961,
            ..rounding
        };
        assert!(
            clamped
                .to_string()
                .contains("colour 2.961 (0–1 scale; colours outside 0–1 were clamped)"),
            "{clamped}"
        );
    }
}
