//! Real spherical harmonics up to degree 3 on the GPU: the basis and its direction gradient, with the
//! constants and signs of `render/sh.rs`. The degree is a compile-time value (one kernel per degree).

use ::gpu::cubecl;
use cubecl::prelude::*;

const C0: f32 = 0.282_094_791_773_878_14_f64 as f32;
const C1: f32 = 0.488_602_511_902_919_9_f64 as f32;
const C20: f32 = 1.092_548_430_592_079_2_f64 as f32;
const C21: f32 = -1.092_548_430_592_079_2_f64 as f32;
const C22: f32 = 0.315_391_565_252_520_05_f64 as f32;
const C23: f32 = -1.092_548_430_592_079_2_f64 as f32;
const C24: f32 = 0.546_274_215_296_039_6_f64 as f32;
const C30: f32 = -0.590_043_589_926_643_5_f64 as f32;
const C31: f32 = 2.890_611_442_640_554_f64 as f32;
const C32: f32 = -0.457_045_799_464_465_8_f64 as f32;
const C33: f32 = 0.373_176_332_590_115_4_f64 as f32;
const C34: f32 = -0.457_045_799_464_465_8_f64 as f32;
const C35: f32 = 1.445_305_721_320_277_f64 as f32;
const C36: f32 = -0.590_043_589_926_643_5_f64 as f32;

/// Basis values at the unit direction (x, y, z); entries past `(degree+1)²` are zero.
#[cube]
pub fn sh_basis(x: f32, y: f32, z: f32, #[comptime] degree: u32) -> Array<f32> {
    let mut b = Array::<f32>::new(16usize);
    #[unroll]
    for k in 0..16usize {
        b[k] = 0.0;
    }
    b[0] = C0;
    if comptime!(degree >= 1) {
        b[1] = -C1 * y;
        b[2] = C1 * z;
        b[3] = -C1 * x;
    }
    if comptime!(degree >= 2) {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        b[4] = C20 * x * y;
        b[5] = C21 * y * z;
        b[6] = C22 * (2.0f32 * zz - xx - yy);
        b[7] = C23 * x * z;
        b[8] = C24 * (xx - yy);
        if comptime!(degree >= 3) {
            b[9] = C30 * y * (3.0f32 * xx - yy);
            b[10] = C31 * x * y * z;
            b[11] = C32 * y * (4.0f32 * zz - xx - yy);
            b[12] = C33 * z * (2.0f32 * zz - 3.0f32 * xx - 3.0f32 * yy);
            b[13] = C34 * x * (4.0f32 * zz - xx - yy);
            b[14] = C35 * z * (xx - yy);
            b[15] = C36 * x * (xx - 3.0f32 * yy);
        }
    }
    b
}

/// Gradient with respect to the direction of `Σ_k v[k]·basis_k(x, y, z)`.
#[cube]
pub fn sh_basis_vjp(
    x: f32,
    y: f32,
    z: f32,
    v: &Array<f32>,
    #[comptime] degree: u32,
) -> (f32, f32, f32) {
    let mut g0 = 0.0f32;
    let mut g1 = 0.0f32;
    let mut g2 = 0.0f32;
    if comptime!(degree >= 1) {
        g1 -= C1 * v[1];
        g2 += C1 * v[2];
        g0 -= C1 * v[3];
    }
    if comptime!(degree >= 2) {
        let xx = x * x;
        let yy = y * y;
        let zz = z * z;
        g0 += C20 * y * v[4];
        g1 += C20 * x * v[4];
        g1 += C21 * z * v[5];
        g2 += C21 * y * v[5];
        g0 -= 2.0f32 * C22 * x * v[6];
        g1 -= 2.0f32 * C22 * y * v[6];
        g2 += 4.0f32 * C22 * z * v[6];
        g0 += C23 * z * v[7];
        g2 += C23 * x * v[7];
        g0 += 2.0f32 * C24 * x * v[8];
        g1 -= 2.0f32 * C24 * y * v[8];
        if comptime!(degree >= 3) {
            g0 += 6.0f32 * C30 * x * y * v[9];
            g1 += 3.0f32 * C30 * (xx - yy) * v[9];
            g0 += C31 * y * z * v[10];
            g1 += C31 * x * z * v[10];
            g2 += C31 * x * y * v[10];
            g0 -= 2.0f32 * C32 * x * y * v[11];
            g1 += C32 * (4.0f32 * zz - xx - 3.0f32 * yy) * v[11];
            g2 += 8.0f32 * C32 * y * z * v[11];
            g0 -= 6.0f32 * C33 * x * z * v[12];
            g1 -= 6.0f32 * C33 * y * z * v[12];
            g2 += C33 * (6.0f32 * zz - 3.0f32 * xx - 3.0f32 * yy) * v[12];
            g0 += C34 * (4.0f32 * zz - 3.0f32 * xx - yy) * v[13];
            g1 -= 2.0f32 * C34 * x * y * v[13];
            g2 += 8.0f32 * C34 * x * z * v[13];
            g0 += 2.0f32 * C35 * x * z * v[14];
            g1 -= 2.0f32 * C35 * y * z * v[14];
            g2 += C35 * (xx - yy) * v[14];
            g0 += 3.0f32 * C36 * (xx - yy) * v[15];
            g1 -= 6.0f32 * C36 * x * y * v[15];
        }
    }
    (g0, g1, g2)
}
