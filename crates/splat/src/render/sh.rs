//! Real spherical harmonics up to degree 3, with the basis constants and sign conventions of the 3DGS
//! reference code (so trained scenes reproduce their colours), and the backward pass.
//!
//! Colour of one Gaussian: `c = max(0, sum_k basis_k(dir) * sh_k + 0.5)`, where `dir` is the unit vector
//! from the camera centre to the Gaussian's mean.

use super::real::{c, Real};

/// Maximum SH degree supported.
pub const MAX_DEGREE: u32 = 3;
/// Coefficients per colour channel at the maximum degree.
pub const MAX_COEFFS: usize = 16;

const C0: f64 = 0.282_094_791_773_878_14;
const C1: f64 = 0.488_602_511_902_919_9;
const C2: [f64; 5] = [
    1.092_548_430_592_079_2,
    -1.092_548_430_592_079_2,
    0.315_391_565_252_520_05,
    -1.092_548_430_592_079_2,
    0.546_274_215_296_039_6,
];
const C3: [f64; 7] = [
    -0.590_043_589_926_643_5,
    2.890_611_442_640_554,
    -0.457_045_799_464_465_8,
    0.373_176_332_590_115_4,
    -0.457_045_799_464_465_8,
    1.445_305_721_320_277,
    -0.590_043_589_926_643_5,
];

/// Evaluates the basis functions for `degree` at the unit direction `d`; entries beyond
/// `(degree+1)^2` are left untouched.
#[inline(always)]
pub fn basis<R: Real>(degree: u32, d: [R; 3], out: &mut [R; MAX_COEFFS]) {
    let [x, y, z] = d;
    out[0] = c(C0);
    if degree == 0 {
        return;
    }
    out[1] = -c::<R>(C1) * y;
    out[2] = c::<R>(C1) * z;
    out[3] = -c::<R>(C1) * x;
    if degree == 1 {
        return;
    }
    let (xx, yy, zz) = (x * x, y * y, z * z);
    out[4] = c::<R>(C2[0]) * x * y;
    out[5] = c::<R>(C2[1]) * y * z;
    out[6] = c::<R>(C2[2]) * (c::<R>(2.0) * zz - xx - yy);
    out[7] = c::<R>(C2[3]) * x * z;
    out[8] = c::<R>(C2[4]) * (xx - yy);
    if degree == 2 {
        return;
    }
    out[9] = c::<R>(C3[0]) * y * (c::<R>(3.0) * xx - yy);
    out[10] = c::<R>(C3[1]) * x * y * z;
    out[11] = c::<R>(C3[2]) * y * (c::<R>(4.0) * zz - xx - yy);
    out[12] = c::<R>(C3[3]) * z * (c::<R>(2.0) * zz - c::<R>(3.0) * xx - c::<R>(3.0) * yy);
    out[13] = c::<R>(C3[4]) * x * (c::<R>(4.0) * zz - xx - yy);
    out[14] = c::<R>(C3[5]) * z * (xx - yy);
    out[15] = c::<R>(C3[6]) * x * (xx - c::<R>(3.0) * yy);
}

/// Gradient with respect to the (unit) direction of `sum_k v_basis[k] * basis_k(d)`.
#[inline(always)]
pub fn basis_vjp<R: Real>(degree: u32, d: [R; 3], v: &[R; MAX_COEFFS]) -> [R; 3] {
    let [x, y, z] = d;
    let mut g = [R::ZERO; 3];
    if degree == 0 {
        return g;
    }
    let k1: R = c(C1);
    g[1] -= k1 * v[1];
    g[2] += k1 * v[2];
    g[0] -= k1 * v[3];
    if degree == 1 {
        return g;
    }
    let two: R = c(2.0);
    let (xx, yy, zz) = (x * x, y * y, z * z);
    let k: [R; 5] = C2.map(c);
    // xy
    g[0] += k[0] * y * v[4];
    g[1] += k[0] * x * v[4];
    // yz
    g[1] += k[1] * z * v[5];
    g[2] += k[1] * y * v[5];
    // 2zz - xx - yy
    g[0] -= two * k[2] * x * v[6];
    g[1] -= two * k[2] * y * v[6];
    g[2] += c::<R>(4.0) * k[2] * z * v[6];
    // xz
    g[0] += k[3] * z * v[7];
    g[2] += k[3] * x * v[7];
    // xx - yy
    g[0] += two * k[4] * x * v[8];
    g[1] -= two * k[4] * y * v[8];
    if degree == 2 {
        return g;
    }
    let k: [R; 7] = C3.map(c);
    let three: R = c(3.0);
    let six: R = c(6.0);
    let eight: R = c(8.0);
    // y(3xx - yy)
    g[0] += six * k[0] * x * y * v[9];
    g[1] += three * k[0] * (xx - yy) * v[9];
    // xyz
    g[0] += k[1] * y * z * v[10];
    g[1] += k[1] * x * z * v[10];
    g[2] += k[1] * x * y * v[10];
    // y(4zz - xx - yy)
    g[0] -= two * k[2] * x * y * v[11];
    g[1] += k[2] * (c::<R>(4.0) * zz - xx - three * yy) * v[11];
    g[2] += eight * k[2] * y * z * v[11];
    // z(2zz - 3xx - 3yy)
    g[0] -= six * k[3] * x * z * v[12];
    g[1] -= six * k[3] * y * z * v[12];
    g[2] += k[3] * (six * zz - three * xx - three * yy) * v[12];
    // x(4zz - xx - yy)
    g[0] += k[4] * (c::<R>(4.0) * zz - three * xx - yy) * v[13];
    g[1] -= two * k[4] * x * y * v[13];
    g[2] += eight * k[4] * x * z * v[13];
    // z(xx - yy)
    g[0] += two * k[5] * x * z * v[14];
    g[1] -= two * k[5] * y * z * v[14];
    g[2] += k[5] * (xx - yy) * v[14];
    // x(xx - 3yy)
    g[0] += three * k[6] * (xx - yy) * v[15];
    g[1] -= six * k[6] * x * y * v[15];
    g
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unit(v: [f64; 3]) -> [f64; 3] {
        let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
        v.map(|a| a / n)
    }

    #[test]
    fn dc_and_degree1_values() {
        let mut b = [0.0f64; 16];
        basis(1, [0.0, 0.0, 1.0], &mut b);
        assert!((b[0] - 0.2820947917738781).abs() < 1e-15);
        assert!((b[2] - 0.4886025119029199).abs() < 1e-15);
        assert_eq!(b[1], 0.0);
        assert_eq!(b[3], 0.0);
    }

    /// The basis is orthonormal on the sphere: a Monte-Carlo-free check through a Fibonacci sphere quadrature.
    #[test]
    fn basis_is_orthonormal() {
        let n = 20000;
        let mut gram = [[0.0f64; 16]; 16];
        let golden = std::f64::consts::PI * (3.0 - 5f64.sqrt());
        for i in 0..n {
            let z = 1.0 - 2.0 * (i as f64 + 0.5) / n as f64;
            let r = (1.0 - z * z).sqrt();
            let phi = golden * i as f64;
            let mut b = [0.0; 16];
            basis(3, [r * phi.cos(), r * phi.sin(), z], &mut b);
            for a in 0..16 {
                for c in 0..16 {
                    gram[a][c] += b[a] * b[c] * 4.0 * std::f64::consts::PI / n as f64;
                }
            }
        }
        for (a, row) in gram.iter().enumerate() {
            for (c, v) in row.iter().enumerate() {
                let want = if a == c { 1.0 } else { 0.0 };
                assert!((v - want).abs() < 2e-3, "gram[{a}][{c}] = {v}");
            }
        }
    }

    #[test]
    fn vjp_matches_finite_differences() {
        let d = unit([0.3, -0.5, 0.8]);
        let v: [f64; 16] = std::array::from_fn(|i| ((i * 7 % 5) as f64 - 2.0) * 0.3 + 0.1);
        for degree in 0..=3 {
            let f = |d: [f64; 3]| {
                let mut b = [0.0; 16];
                basis(degree, d, &mut b);
                (0..16).map(|k| b[k] * v[k]).sum::<f64>()
            };
            let g = basis_vjp(degree, d, &v);
            for a in 0..3 {
                let h = 1e-6;
                let mut dp = d;
                let mut dm = d;
                dp[a] += h;
                dm[a] -= h;
                let fd = (f(dp) - f(dm)) / (2.0 * h);
                assert!(
                    (fd - g[a]).abs() < 1e-7,
                    "degree {degree} axis {a}: {fd} vs {}",
                    g[a]
                );
            }
        }
    }
}
