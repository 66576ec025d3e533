//! Stage (a) on the GPU: per-Gaussian EWA projection and SH colour, and its backward; one unit per
//! Gaussian. The math is that of `render/project.rs` (the CPU reference) line for line, in f32.
//!
//! Device layouts (one record per Gaussian):
//! - splats (f32 × [`SPLAT_F`]): mean x, y, conic a, b, c, opacity, r, g, b, depth.
//! - info (u32 × [`INFO_U`]): radius (0 = culled), tile rect x0, y0, x1, y1, clamped colour bits,
//!   covered tile count (0 unless drawable), depth sort key (`u32::MAX` unless drawable).
//! - splat gradients (f32 × [`GRAD_F`]): mean x, y, conic a, b, c, opacity, r, g, b, depth.
//! - camera (f32 × [`CAM_F`]): fx, fy, cx, cy, R (9, row-major), t (3), centre (3), lim_x (2), lim_y (2).

use ::gpu::cubecl;
use cubecl::prelude::*;

use super::sh::{sh_basis, sh_basis_vjp};
use crate::render::{ALPHA_MIN, LOW_PASS, NEAR_PLANE, TILE};

pub const SPLAT_F: usize = 10;
pub const INFO_U: usize = 8;
pub const GRAD_F: usize = 10;
pub const CAM_F: usize = 23;

/// Intermediate values of the projection, shared by the forward and backward kernels.
#[derive(CubeType, Clone, Copy)]
pub struct Geom {
    pub ok: bool,
    pub px: f32,
    pub py: f32,
    pub pz: f32,
    /// Normalised quaternion and its norm.
    pub qw: f32,
    pub qx: f32,
    pub qy: f32,
    pub qz: f32,
    pub qnorm: f32,
    pub s0: f32,
    pub s1: f32,
    pub s2: f32,
    /// Camera-space covariance (symmetric): 00, 01, 02, 11, 12, 22.
    pub c00: f32,
    pub c01: f32,
    pub c02: f32,
    pub c11: f32,
    pub c12: f32,
    pub c22: f32,
    pub tx: f32,
    pub ty: f32,
    pub clamped_x: bool,
    pub clamped_y: bool,
    /// Dilated 2D covariance (a, b, c).
    pub a: f32,
    pub b: f32,
    pub c: f32,
}

#[cube]
fn finite(v: f32) -> bool {
    !v.is_nan() && !v.is_inf()
}

/// Rotation matrix (row-major, 9 entries) of the unit quaternion (w, x, y, z).
#[cube]
pub fn quat_matrix(w: f32, x: f32, y: f32, z: f32) -> Array<f32> {
    let mut r = Array::<f32>::new(9usize);
    r[0] = 1.0f32 - 2.0f32 * (y * y + z * z);
    r[1] = 2.0f32 * (x * y - w * z);
    r[2] = 2.0f32 * (x * z + w * y);
    r[3] = 2.0f32 * (x * y + w * z);
    r[4] = 1.0f32 - 2.0f32 * (x * x + z * z);
    r[5] = 2.0f32 * (y * z - w * x);
    r[6] = 2.0f32 * (x * z - w * y);
    r[7] = 2.0f32 * (y * z + w * x);
    r[8] = 1.0f32 - 2.0f32 * (x * x + y * y);
    r
}

#[cube]
pub fn geometry(means: &[f32], log_scales: &[f32], quats: &[f32], cam: &[f32], i: usize) -> Geom {
    let mx = means[3 * i];
    let my = means[3 * i + 1];
    let mz = means[3 * i + 2];
    let px = cam[4] * mx + cam[5] * my + cam[6] * mz + cam[13];
    let py = cam[7] * mx + cam[8] * my + cam[9] * mz + cam[14];
    let pz = cam[10] * mx + cam[11] * my + cam[12] * mz + cam[15];
    let qw0 = quats[4 * i];
    let qx0 = quats[4 * i + 1];
    let qy0 = quats[4 * i + 2];
    let qz0 = quats[4 * i + 3];
    let qnorm = (qw0 * qw0 + qx0 * qx0 + qy0 * qy0 + qz0 * qz0).sqrt();
    // `!(z > near)` also rejects NaN.
    let ok = pz > NEAR_PLANE as f32
        && finite(px)
        && finite(py)
        && finite(pz)
        && qnorm > 0.0
        && finite(qnorm);
    let qw = qw0 / qnorm;
    let qx = qx0 / qnorm;
    let qy = qy0 / qnorm;
    let qz = qz0 / qnorm;
    let s0 = log_scales[3 * i].exp();
    let s1 = log_scales[3 * i + 1].exp();
    let s2 = log_scales[3 * i + 2].exp();
    // M = Rq diag(s); Σ = M Mᵀ.
    let rq = quat_matrix(qw, qx, qy, qz);
    let m00 = rq[0] * s0;
    let m01 = rq[1] * s1;
    let m02 = rq[2] * s2;
    let m10 = rq[3] * s0;
    let m11 = rq[4] * s1;
    let m12 = rq[5] * s2;
    let m20 = rq[6] * s0;
    let m21 = rq[7] * s1;
    let m22 = rq[8] * s2;
    let mut sig = Array::<f32>::new(9usize);
    sig[0] = m00 * m00 + m01 * m01 + m02 * m02;
    sig[1] = m00 * m10 + m01 * m11 + m02 * m12;
    sig[2] = m00 * m20 + m01 * m21 + m02 * m22;
    sig[3] = sig[1];
    sig[4] = m10 * m10 + m11 * m11 + m12 * m12;
    sig[5] = m10 * m20 + m11 * m21 + m12 * m22;
    sig[6] = sig[2];
    sig[7] = sig[5];
    sig[8] = m20 * m20 + m21 * m21 + m22 * m22;
    // Σc = R Σ Rᵀ: first RΣ, then (RΣ) Rᵀ.
    let mut rs = Array::<f32>::new(9usize);
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            rs[a * 3 + b] = cam[4 + a * 3] * sig[b]
                + cam[4 + a * 3 + 1] * sig[3 + b]
                + cam[4 + a * 3 + 2] * sig[6 + b];
        }
    }
    let mut cc = Array::<f32>::new(9usize);
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            cc[a * 3 + b] = rs[a * 3] * cam[4 + b * 3]
                + rs[a * 3 + 1] * cam[4 + b * 3 + 1]
                + rs[a * 3 + 2] * cam[4 + b * 3 + 2];
        }
    }
    let fx = cam[0];
    let fy = cam[1];
    let u = px / pz;
    let v = py / pz;
    let ux = f32::min(f32::max(u, -cam[19]), cam[20]);
    let vy = f32::min(f32::max(v, -cam[21]), cam[22]);
    let clamped_x = u < -cam[19] || u > cam[20];
    let clamped_y = v < -cam[21] || v > cam[22];
    let tx = select(clamped_x, pz * ux, px);
    let ty = select(clamped_y, pz * vy, py);
    let z2 = pz * pz;
    let j00 = fx / pz;
    let j02 = -fx * tx / z2;
    let j11 = fy / pz;
    let j12 = -fy * ty / z2;
    // S = J Σc Jᵀ with J = [[j00, 0, j02], [0, j11, j12]].
    let jc00 = j00 * cc[0] + j02 * cc[6];
    let jc01 = j00 * cc[1] + j02 * cc[7];
    let jc02 = j00 * cc[2] + j02 * cc[8];
    let jc11 = j11 * cc[4] + j12 * cc[7];
    let jc12 = j11 * cc[5] + j12 * cc[8];
    let low = LOW_PASS as f32;
    Geom {
        ok,
        px,
        py,
        pz,
        qw,
        qx,
        qy,
        qz,
        qnorm,
        s0,
        s1,
        s2,
        c00: cc[0],
        c01: cc[1],
        c02: cc[2],
        c11: cc[4],
        c12: cc[5],
        c22: cc[8],
        tx,
        ty,
        clamped_x,
        clamped_y,
        a: jc00 * j00 + jc02 * j02 + low,
        b: jc01 * j11 + jc02 * j12,
        c: jc11 * j11 + jc12 * j12 + low,
    }
}

/// Unit direction camera centre → mean, and the length divided by (1 for a zero vector).
#[cube]
fn view_dir(means: &[f32], cam: &[f32], i: usize) -> (f32, f32, f32, f32) {
    view_dir_from(means, cam[16], cam[17], cam[18], i)
}

/// [`view_dir`] from the camera centre (cx, cy, cz).
#[cube]
fn view_dir_from(means: &[f32], cx: f32, cy: f32, cz: f32, i: usize) -> (f32, f32, f32, f32) {
    let dx = means[3 * i] - cx;
    let dy = means[3 * i + 1] - cy;
    let dz = means[3 * i + 2] - cz;
    let n = (dx * dx + dy * dy + dz * dz).sqrt();
    let pos = n > 0.0;
    let len = select(pos, n, 1.0f32);
    let s = select(pos, 1.0f32 / n, 0.0f32);
    (dx * s, dy * s, dz * s, len)
}

/// Stage (a) forward. `degree` is the SH degree (0..=3). With `keep_faint`, every Gaussian whose
/// geometry is drawable gets its tiles and depth key whatever its opacity (a NaN one is stored as 0):
/// the tile lists of a view whose geometry is then kept while the opacities move (see
/// `gpu::frozen`). The raster kernels skip a Gaussian below 1/255 opacity at every pixel, so the
/// extra entries change no output.
#[cube(launch)]
pub fn project_forward(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    opacity_logits: &[f32],
    sh: &[f32],
    cam: &[f32],
    n: u32,
    tiles_x: u32,
    tiles_y: u32,
    splats: &mut [f32],
    info: &mut [u32],
    #[comptime] degree: u32,
    #[comptime] keep_faint: bool,
) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        #[unroll]
        for k in 0..10usize {
            splats[i * 10 + k] = 0.0;
        }
        #[unroll]
        for k in 0..7usize {
            info[i * 8 + k] = 0u32;
        }
        info[i * 8 + 7] = u32::MAX;
        let g = geometry(means, log_scales, quats, cam, i);
        let det = g.a * g.c - g.b * g.b;
        let mx = cam[0] * g.px / g.pz + cam[2];
        let my = cam[1] * g.py / g.pz + cam[3];
        let mid = 0.5f32 * (g.a + g.c);
        let lambda = mid + f32::max(mid * mid - det, 0.1f32).sqrt();
        let radius_f = (3.0f32 * lambda.sqrt()).ceil();
        let tile = TILE as f32;
        let x0 = clamp_tile(((mx - radius_f) / tile).floor(), tiles_x);
        let x1 = clamp_tile(((mx + radius_f) / tile).ceil(), tiles_x);
        let y0 = clamp_tile(((my - radius_f) / tile).floor(), tiles_y);
        let y1 = clamp_tile(((my + radius_f) / tile).ceil(), tiles_y);
        let radius = f32::min(radius_f, 1e9f32) as u32;
        let opacity = opacity_of(opacity_logits, i);
        let visible = g.ok
            && det > 0.0
            && finite(det)
            && finite(radius_f)
            && finite(mx)
            && finite(my)
            && radius > 0
            && x1 > x0
            && y1 > y0
            && (keep_faint || !opacity.is_nan());
        if visible {
            splats[i * 10] = mx;
            splats[i * 10 + 1] = my;
            splats[i * 10 + 2] = g.c / det;
            splats[i * 10 + 3] = -g.b / det;
            splats[i * 10 + 4] = g.a / det;
            splats[i * 10 + 9] = g.pz;
            info[i * 8] = radius;
            info[i * 8 + 1] = x0;
            info[i * 8 + 2] = y0;
            info[i * 8 + 3] = x1;
            info[i * 8 + 4] = y1;
            write_appearance(means, sh, cam, i, opacity, splats, info, degree);
            // Below 1/255 opacity no pixel can pass the alpha test: not binned (unless kept).
            if keep_faint || opacity >= ALPHA_MIN as f32 {
                info[i * 8 + 6] = (x1 - x0) * (y1 - y0);
                info[i * 8 + 7] = u32::reinterpret(g.pz);
            }
        }
    }
}

/// The opacity of Gaussian `i`: the sigmoid of its logit, NaN for a NaN logit.
#[cube]
fn opacity_of(opacity_logits: &[f32], i: usize) -> f32 {
    1.0f32 / (1.0f32 + (-opacity_logits[i]).exp())
}

/// Writes the appearance of a drawable Gaussian: its opacity (0 for NaN: no pixel then takes it, where
/// a GPU's `min(0.99, NaN)` might) and its colour `0.5 + Σ basis·sh` clamped at 0, with the clamped
/// channels' bits.
#[cube]
fn write_appearance(
    means: &[f32],
    sh: &[f32],
    cam: &[f32],
    i: usize,
    opacity: f32,
    splats: &mut [f32],
    info: &mut [u32],
    #[comptime] degree: u32,
) {
    splats[i * 10 + 5] = select(opacity.is_nan(), 0.0f32, opacity);
    let (dx, dy, dz, _len) = view_dir(means, cam, i);
    let basis = sh_basis(dx, dy, dz, degree);
    let k = comptime!(((degree + 1) * (degree + 1)) as usize);
    let mut clamped = 0u32;
    #[unroll]
    for ch in 0..3usize {
        let mut col = 0.5f32;
        #[unroll]
        for kk in 0..k {
            col += basis[kk] * sh[(i * k + kk) * 3 + ch];
        }
        if col < 0.0 {
            col = 0.0;
            clamped |= 1u32 << ch as u32;
        }
        splats[i * 10 + 6 + ch] = col;
    }
    info[i * 8 + 5] = clamped;
}

/// Stage (a) forward for a kept geometry: rewrites the opacity and colour of every drawable Gaussian
/// (`info`'s radius above 0) in `splats` and `info` made by [`project_forward`] with `keep_faint` for
/// the same means, scales, rotations and camera. The same arithmetic as that kernel, so the values
/// are the same, bit for bit.
#[cube(launch)]
pub fn project_appearance(
    means: &[f32],
    opacity_logits: &[f32],
    sh: &[f32],
    cam: &[f32],
    n: u32,
    splats: &mut [f32],
    info: &mut [u32],
    #[comptime] degree: u32,
) {
    let i = ABSOLUTE_POS;
    if i < n as usize && info[i * 8] > 0 {
        let opacity = opacity_of(opacity_logits, i);
        write_appearance(means, sh, cam, i, opacity, splats, info, degree);
    }
}

/// [`project_appearance`] for a pair of fits of one scene (a launch for both): Gaussians `0..n` are the
/// first fit's, `n..2n` the second's (parameters in `means`, `opacity_logits`, `sh`); each half takes
/// its kept view's geometry (`kept_splats`/`kept_info` from `cam`, the `_b` ones from `cam_b`, both
/// made by [`project_forward`] with `keep_faint` for `n` Gaussians) and its own opacity and colour,
/// written to `splats` and `info` (2n records; the kept views stay as they are, so both halves may
/// share one). The values are those [`project_appearance`] writes, bit for bit.
#[cube(launch)]
pub fn project_appearance_pair(
    means: &[f32],
    opacity_logits: &[f32],
    sh: &[f32],
    cam: &[f32],
    kept_splats: &[f32],
    kept_info: &[u32],
    cam_b: &[f32],
    kept_splats_b: &[f32],
    kept_info_b: &[u32],
    n: u32,
    splats: &mut [f32],
    info: &mut [u32],
    #[comptime] degree: u32,
) {
    let i = ABSOLUTE_POS;
    let half = n as usize;
    if i < 2 * half {
        let second = i >= half;
        let j = i % half;
        if second {
            copy_record(kept_splats_b, kept_info_b, j, splats, info, i);
        } else {
            copy_record(kept_splats, kept_info, j, splats, info, i);
        }
        if info[i * 8] > 0 {
            let opacity = opacity_of(opacity_logits, i);
            if second {
                write_appearance(means, sh, cam_b, i, opacity, splats, info, degree);
            } else {
                write_appearance(means, sh, cam, i, opacity, splats, info, degree);
            }
        }
    }
}

/// Copies record `from` of a view's splats and info to record `to`.
#[cube]
fn copy_record(
    kept_splats: &[f32],
    kept_info: &[u32],
    from: usize,
    splats: &mut [f32],
    info: &mut [u32],
    to: usize,
) {
    #[unroll]
    for k in 0..10usize {
        splats[to * 10 + k] = kept_splats[from * 10 + k];
    }
    #[unroll]
    for k in 0..8usize {
        info[to * 8 + k] = kept_info[from * 8 + k];
    }
}

#[cube]
fn clamp_tile(v: f32, hi: u32) -> u32 {
    f32::min(f32::max(v, 0.0), hi as f32) as u32
}

/// Stage (a) backward: parameter gradients from the splat gradients (overwrites every output). Without
/// `geometry`, the opacity and SH gradients alone (the means', scales' and rotations' are written as 0):
/// the backward of a view whose geometry is kept. Gaussians from `half` on are seen from `cam_b` (the
/// second fit of a pair, [`project_appearance_pair`]; kept geometry only), the others from `cam`.
#[cube(launch)]
pub fn project_backward(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    sh: &[f32],
    cam: &[f32],
    cam_b: &[f32],
    half: u32,
    n: u32,
    splats: &[f32],
    info: &[u32],
    grads: &[f32],
    g_means: &mut [f32],
    g_log_scales: &mut [f32],
    g_quats: &mut [f32],
    g_logits: &mut [f32],
    g_sh: &mut [f32],
    #[comptime] degree: u32,
    #[comptime] with_geometry: bool,
) {
    let i = ABSOLUTE_POS;
    if i < n as usize {
        let k = comptime!(((degree + 1) * (degree + 1)) as usize);
        #[unroll]
        for a in 0..3usize {
            g_means[3 * i + a] = 0.0;
            g_log_scales[3 * i + a] = 0.0;
        }
        #[unroll]
        for a in 0..4usize {
            g_quats[4 * i + a] = 0.0;
        }
        g_logits[i] = 0.0;
        #[unroll]
        for a in 0..comptime!(3 * k) {
            g_sh[i * 3 * k + a] = 0.0;
        }
        // A radius above 0 means the geometry was drawable (`g.ok` included).
        if info[i * 8] > 0 {
            // The second fit's half of a pair (kept geometry only) is seen from `cam_b`.
            let mut second = false;
            if comptime!(!with_geometry) {
                second = i >= half as usize;
            }
            project_backward_one(
                means,
                log_scales,
                quats,
                sh,
                cam,
                cam_b,
                second,
                splats,
                info,
                grads,
                g_means,
                g_log_scales,
                g_quats,
                g_logits,
                g_sh,
                i,
                degree,
                with_geometry,
            );
        }
    }
}

#[cube]
fn project_backward_one(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    sh: &[f32],
    cam: &[f32],
    cam_b: &[f32],
    second: bool,
    splats: &[f32],
    info: &[u32],
    grads: &[f32],
    g_means: &mut [f32],
    g_log_scales: &mut [f32],
    g_quats: &mut [f32],
    g_logits: &mut [f32],
    g_sh: &mut [f32],
    i: usize,
    #[comptime] degree: u32,
    #[comptime] with_geometry: bool,
) {
    let k = comptime!(((degree + 1) * (degree + 1)) as usize);
    let v_op = grads[i * 10 + 5];
    let o = splats[i * 10 + 5];
    g_logits[i] = v_op * o * (1.0 - o);

    // Colour: SH coefficients and the view direction.
    let clamped = info[i * 8 + 5];
    let mut v_col = Array::<f32>::new(3usize);
    #[unroll]
    for ch in 0..3usize {
        v_col[ch] = select(
            (clamped >> ch as u32) & 1u32 != 0,
            0.0f32,
            grads[i * 10 + 6 + ch],
        );
    }
    let mut vm0 = 0.0f32;
    let mut vm1 = 0.0f32;
    let mut vm2 = 0.0f32;
    if v_col[0] != 0.0 || v_col[1] != 0.0 || v_col[2] != 0.0 {
        let mut centre = Array::<f32>::new(3usize);
        #[unroll]
        for a in 0..3usize {
            centre[a] = select(second, cam_b[16 + a], cam[16 + a]);
        }
        let (dx, dy, dz, len) = view_dir_from(means, centre[0], centre[1], centre[2], i);
        let basis = sh_basis(dx, dy, dz, degree);
        let mut v_basis = Array::<f32>::new(16usize);
        #[unroll]
        for kk in 0..k {
            let mut vb = 0.0f32;
            #[unroll]
            for ch in 0..3usize {
                g_sh[(i * k + kk) * 3 + ch] = basis[kk] * v_col[ch];
                vb += sh[(i * k + kk) * 3 + ch] * v_col[ch];
            }
            v_basis[kk] = vb;
        }
        if comptime!(with_geometry) {
            let (gx, gy, gz) = sh_basis_vjp(dx, dy, dz, &v_basis, degree);
            let dot = dx * gx + dy * gy + dz * gz;
            vm0 += (gx - dx * dot) / len;
            vm1 += (gy - dy * dot) / len;
            vm2 += (gz - dz * dot) / len;
        }
    }
    if comptime!(with_geometry) {
        geometry_backward(
            means,
            log_scales,
            quats,
            cam,
            splats,
            grads,
            g_means,
            g_log_scales,
            g_quats,
            i,
            (vm0, vm1, vm2),
        );
    }
}

/// The means', scales' and rotations' part of [`project_backward_one`]; `vm` is the means' gradient
/// through the colours' view direction.
#[cube]
#[allow(clippy::too_many_arguments)]
fn geometry_backward(
    means: &[f32],
    log_scales: &[f32],
    quats: &[f32],
    cam: &[f32],
    splats: &[f32],
    grads: &[f32],
    g_means: &mut [f32],
    g_log_scales: &mut [f32],
    g_quats: &mut [f32],
    i: usize,
    vm: (f32, f32, f32),
) {
    let g = geometry(means, log_scales, quats, cam, i);
    let (mut vm0, mut vm1, mut vm2) = vm;
    let v_mx = grads[i * 10];
    let v_my = grads[i * 10 + 1];
    let v_ca = grads[i * 10 + 2];
    let v_cb = grads[i * 10 + 3];
    let v_cc = grads[i * 10 + 4];
    let v_depth = grads[i * 10 + 9];

    // Conic = S⁻¹ → V_S = -P G P (the off-diagonal conic entry stands for both off-diagonal elements).
    let p00 = splats[i * 10 + 2];
    let p01 = splats[i * 10 + 3];
    let p11 = splats[i * 10 + 4];
    let g00 = v_ca;
    let g01 = 0.5f32 * v_cb;
    let g11 = v_cc;
    let pg00 = p00 * g00 + p01 * g01;
    let pg01 = p00 * g01 + p01 * g11;
    let pg10 = p01 * g00 + p11 * g01;
    let pg11 = p01 * g01 + p11 * g11;
    let vs00 = -(pg00 * p00 + pg01 * p01);
    let vs01 = -(pg00 * p01 + pg01 * p11);
    let vs10 = -(pg10 * p00 + pg11 * p01);
    let vs11 = -(pg10 * p01 + pg11 * p11);

    // S = J Σc Jᵀ + 0.3 I → V_Σc = Jᵀ V_S J, V_J = 2 V_S J Σc.
    let fx = cam[0];
    let fy = cam[1];
    let z = g.pz;
    let z2 = z * z;
    let z3 = z2 * z;
    let mut jac = Array::<f32>::new(6usize);
    jac[0] = fx / z;
    jac[1] = 0.0;
    jac[2] = -fx * g.tx / z2;
    jac[3] = 0.0;
    jac[4] = fy / z;
    jac[5] = -fy * g.ty / z2;
    let mut vsj = Array::<f32>::new(6usize);
    #[unroll]
    for b in 0..3usize {
        vsj[b] = vs00 * jac[b] + vs01 * jac[3 + b];
        vsj[3 + b] = vs10 * jac[b] + vs11 * jac[3 + b];
    }
    let mut vcc = Array::<f32>::new(9usize);
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            vcc[a * 3 + b] = jac[a] * vsj[b] + jac[3 + a] * vsj[3 + b];
        }
    }
    let mut cov = Array::<f32>::new(9usize);
    cov[0] = g.c00;
    cov[1] = g.c01;
    cov[2] = g.c02;
    cov[3] = g.c01;
    cov[4] = g.c11;
    cov[5] = g.c12;
    cov[6] = g.c02;
    cov[7] = g.c12;
    cov[8] = g.c22;
    let mut vj = Array::<f32>::new(6usize);
    #[unroll]
    for a in 0..2usize {
        #[unroll]
        for b in 0..3usize {
            vj[a * 3 + b] = 2.0f32
                * (vsj[a * 3] * cov[b] + vsj[a * 3 + 1] * cov[3 + b] + vsj[a * 3 + 2] * cov[6 + b]);
        }
    }
    let mut vpx = 0.0f32;
    let mut vpy = 0.0f32;
    let mut vpz = -fx / z2 * vj[0] - fy / z2 * vj[4]
        + 2.0f32 * fx * g.tx / z3 * vj[2]
        + 2.0f32 * fy * g.ty / z3 * vj[5];
    let v_tx = -fx / z2 * vj[2];
    let v_ty = -fy / z2 * vj[5];
    if g.clamped_x {
        vpz += v_tx * (g.tx / z);
    } else {
        vpx += v_tx;
    }
    if g.clamped_y {
        vpz += v_ty * (g.ty / z);
    } else {
        vpy += v_ty;
    }
    vpx += fx / z * v_mx;
    vpy += fy / z * v_my;
    vpz += -fx * g.px / z2 * v_mx - fy * g.py / z2 * v_my + v_depth;

    // p = R m + t.
    vm0 += cam[4] * vpx + cam[7] * vpy + cam[10] * vpz;
    vm1 += cam[5] * vpx + cam[8] * vpy + cam[11] * vpz;
    vm2 += cam[6] * vpx + cam[9] * vpy + cam[12] * vpz;
    g_means[3 * i] = vm0;
    g_means[3 * i + 1] = vm1;
    g_means[3 * i + 2] = vm2;

    // Σc = R Σ Rᵀ → V_Σ = Rᵀ V_Σc R.
    let mut t1 = Array::<f32>::new(9usize);
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            t1[a * 3 + b] =
                cam[4 + a] * vcc[b] + cam[4 + 3 + a] * vcc[3 + b] + cam[4 + 6 + a] * vcc[6 + b];
        }
    }
    let mut vsig = Array::<f32>::new(9usize);
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            vsig[a * 3 + b] = t1[a * 3] * cam[4 + b]
                + t1[a * 3 + 1] * cam[4 + 3 + b]
                + t1[a * 3 + 2] * cam[4 + 6 + b];
        }
    }
    // Σ = M Mᵀ → V_M = 2 V_Σ M, M = Rq diag(s).
    let rq = quat_matrix(g.qw, g.qx, g.qy, g.qz);
    let mut sc = Array::<f32>::new(3usize);
    sc[0] = g.s0;
    sc[1] = g.s1;
    sc[2] = g.s2;
    let mut vrq = Array::<f32>::new(9usize);
    let mut vs0 = 0.0f32;
    let mut vs1 = 0.0f32;
    let mut vs2 = 0.0f32;
    #[unroll]
    for a in 0..3usize {
        #[unroll]
        for b in 0..3usize {
            let vm = 2.0f32
                * (vsig[a * 3] * rq[b] + vsig[a * 3 + 1] * rq[3 + b] + vsig[a * 3 + 2] * rq[6 + b])
                * sc[b];
            vrq[a * 3 + b] = vm * sc[b];
            let contrib = vm * rq[a * 3 + b];
            if comptime!(b == 0) {
                vs0 += contrib;
            } else if comptime!(b == 1) {
                vs1 += contrib;
            } else {
                vs2 += contrib;
            }
        }
    }
    g_log_scales[3 * i] = vs0 * g.s0;
    g_log_scales[3 * i + 1] = vs1 * g.s1;
    g_log_scales[3 * i + 2] = vs2 * g.s2;
    // Through the rotation matrix of the unit quaternion, then the normalisation.
    let w = g.qw;
    let x = g.qx;
    let y = g.qy;
    let zq = g.qz;
    let gw =
        2.0f32 * (-zq * vrq[1] + y * vrq[2] + zq * vrq[3] - x * vrq[5] - y * vrq[6] + x * vrq[7]);
    let gx = 2.0f32
        * (y * vrq[1] + zq * vrq[2] + y * vrq[3] - 2.0f32 * x * vrq[4] - w * vrq[5]
            + zq * vrq[6]
            + w * vrq[7]
            - 2.0f32 * x * vrq[8]);
    let gy = 2.0f32
        * (-2.0f32 * y * vrq[0] + x * vrq[1] + w * vrq[2] + x * vrq[3] + zq * vrq[5] - w * vrq[6]
            + zq * vrq[7]
            - 2.0f32 * y * vrq[8]);
    let gz = 2.0f32
        * (-2.0f32 * zq * vrq[0] - w * vrq[1] + x * vrq[2] + w * vrq[3] - 2.0f32 * zq * vrq[4]
            + y * vrq[5]
            + x * vrq[6]
            + y * vrq[7]);
    let dot = w * gw + x * gx + y * gy + zq * gz;
    g_quats[4 * i] = (gw - w * dot) / g.qnorm;
    g_quats[4 * i + 1] = (gx - x * dot) / g.qnorm;
    g_quats[4 * i + 2] = (gy - y * dot) / g.qnorm;
    g_quats[4 * i + 3] = (gz - zq * dot) / g.qnorm;
}
