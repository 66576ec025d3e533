//! Stage (a): per-Gaussian projection to the screen (EWA splatting as in gsplat/3DGS) and its backward.
//!
//! Forward, for one Gaussian with mean `m`, log-scales `l`, quaternion `q` (w, x, y, z), opacity logit and
//! SH coefficients:
//! - `p = R m + t` (camera frame), culled unless `p.z > NEAR_PLANE`;
//! - `Σ = M Mᵀ` with `M = rot(q/|q|) diag(exp(l))`, `Σc = R Σ Rᵀ`;
//! - EWA: `S = J Σc Jᵀ + 0.3 I` with the perspective Jacobian `J` evaluated at `(tx, ty, z)`, where
//!   `tx/z` is clamped to 1.3x the half field of view (as gsplat/3DGS do, so Gaussians far outside the view
//!   do not get absurd footprints); the mean itself is projected unclamped;
//! - conic `S⁻¹`, radius `ceil(3 sqrt(λmax(S)))` (3DGS's eigenvalue rule) and the tile rectangle it covers;
//! - colour from SH along the unit direction camera centre → mean, `+0.5`, clamped at 0.

use super::real::{c, Real};
use super::sh;
use super::Params;
use crate::cameras::Camera;

/// Gaussians at or closer than this camera depth are not rendered.
pub const NEAR_PLANE: f64 = 0.01;
/// Low-pass filter added to the diagonal of every screen-space covariance (pixels²).
pub const LOW_PASS: f64 = 0.3;
/// Alphas below this are skipped by the rasteriser.
pub const ALPHA_MIN: f64 = 1.0 / 255.0;
/// Alphas are clamped to at most this.
pub const ALPHA_MAX: f64 = 0.99;
/// A pixel stops accepting Gaussians once its transmittance would drop below this.
pub const T_MIN: f64 = 1e-4;
/// Tile edge length in pixels.
pub const TILE: u32 = 16;

/// A camera converted to the working float type, with the values the projection needs.
#[derive(Clone, Debug)]
pub struct CameraR<R> {
    pub width: u32,
    pub height: u32,
    pub fx: R,
    pub fy: R,
    pub cx: R,
    pub cy: R,
    pub rot: [[R; 3]; 3],
    pub trans: [R; 3],
    pub center: [R; 3],
    /// Clamp limits of x/z and y/z for the Jacobian: (negative side, positive side).
    pub lim_x: (R, R),
    pub lim_y: (R, R),
}

impl<R: Real> CameraR<R> {
    pub fn new(cam: &Camera) -> Self {
        let (w, h) = (cam.width as f64, cam.height as f64);
        let tan_x = 0.5 * w / cam.fx;
        let tan_y = 0.5 * h / cam.fy;
        Self {
            width: cam.width,
            height: cam.height,
            fx: c(cam.fx),
            fy: c(cam.fy),
            cx: c(cam.cx),
            cy: c(cam.cy),
            rot: cam.rotation.map(|r| r.map(c)),
            trans: cam.translation.map(c),
            center: cam.center().map(c),
            lim_x: (
                c(cam.cx / cam.fx + 0.3 * tan_x),
                c((w - cam.cx) / cam.fx + 0.3 * tan_x),
            ),
            lim_y: (
                c(cam.cy / cam.fy + 0.3 * tan_y),
                c((h - cam.cy) / cam.fy + 0.3 * tan_y),
            ),
        }
    }

    pub fn tiles(&self) -> (u32, u32) {
        (self.width.div_ceil(TILE), self.height.div_ceil(TILE))
    }
}

/// One Gaussian projected to the screen: everything the rasteriser needs, in one record that fills
/// exactly one 64-byte cache line in f32.
#[derive(Clone, Copy, Debug, Default)]
#[repr(C, align(64))]
pub struct Splat<R> {
    /// Pixel coordinates of the projected mean.
    pub mean: [R; 2],
    /// Upper triangle of the inverse 2D covariance (a, b, c): σ = ½(a dx² + c dy²) + b dx dy.
    pub conic: [R; 3],
    pub opacity: R,
    /// Half height and half width in pixels of the bounding box of the region where alpha can reach
    /// 1/255 (σ ≤ ln(255·o), slightly enlarged), used to skip rows and column groups.
    pub half_height: R,
    pub half_width: R,
    pub color: [R; 3],
    /// Camera-space z.
    pub depth: R,
    /// Screen radius in pixels; 0 = culled.
    pub radius: u32,
    /// Covered tiles: x0, y0, x1, y1 (exclusive ends).
    pub tiles: [u16; 4],
    /// Bit k set when colour channel k was clamped at 0 (its gradient is then zero).
    pub clamped: u8,
}

impl<R: Real> Splat<R> {
    /// Whether this Gaussian can contribute to any pixel.
    #[inline]
    pub fn is_drawable(&self) -> bool {
        // Below 1/255 opacity no pixel can pass the alpha test.
        self.radius > 0 && self.opacity >= c(ALPHA_MIN)
    }

    /// Covered tiles as x0, y0, x1, y1 (exclusive ends).
    #[cfg(test)]
    pub fn tile_rect(&self) -> [u32; 4] {
        self.tiles.map(u32::from)
    }
}

#[inline(always)]
fn matmul3<R: Real>(a: &[[R; 3]; 3], b: &[[R; 3]; 3]) -> [[R; 3]; 3] {
    let mut o = [[R::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j];
        }
    }
    o
}

#[inline(always)]
fn transpose3<R: Real>(a: &[[R; 3]; 3]) -> [[R; 3]; 3] {
    let mut o = [[R::ZERO; 3]; 3];
    for i in 0..3 {
        for j in 0..3 {
            o[i][j] = a[j][i];
        }
    }
    o
}

/// Rotation matrix of a unit quaternion (w, x, y, z).
#[inline(always)]
pub fn quat_to_rot<R: Real>(q: [R; 4]) -> [[R; 3]; 3] {
    let [w, x, y, z] = q;
    let one = R::ONE;
    let two: R = c(2.0);
    [
        [
            one - two * (y * y + z * z),
            two * (x * y - w * z),
            two * (x * z + w * y),
        ],
        [
            two * (x * y + w * z),
            one - two * (x * x + z * z),
            two * (y * z - w * x),
        ],
        [
            two * (x * z - w * y),
            two * (y * z + w * x),
            one - two * (x * x + y * y),
        ],
    ]
}

/// Gradient with respect to the unit quaternion given the gradient `v` of its rotation matrix.
#[inline(always)]
fn quat_to_rot_vjp<R: Real>(q: [R; 4], v: &[[R; 3]; 3]) -> [R; 4] {
    let [w, x, y, z] = q;
    let two: R = c(2.0);
    let gw = -z * v[0][1] + y * v[0][2] + z * v[1][0] - x * v[1][2] - y * v[2][0] + x * v[2][1];
    let gx = y * v[0][1] + z * v[0][2] + y * v[1][0] - two * x * v[1][1] - w * v[1][2]
        + z * v[2][0]
        + w * v[2][1]
        - two * x * v[2][2];
    let gy = -two * y * v[0][0] + x * v[0][1] + w * v[0][2] + x * v[1][0] + z * v[1][2]
        - w * v[2][0]
        + z * v[2][1]
        - two * y * v[2][2];
    let gz = -two * z * v[0][0] - w * v[0][1] + x * v[0][2] + w * v[1][0] - two * z * v[1][1]
        + y * v[1][2]
        + x * v[2][0]
        + y * v[2][1];
    [two * gw, two * gx, two * gy, two * gz]
}

#[inline(always)]
pub fn sigmoid<R: Real>(x: R) -> R {
    R::ONE / (R::ONE + (-x).exp())
}

/// Intermediate values of the projection of one Gaussian, shared by the forward and backward passes.
struct Geometry<R> {
    pc: [R; 3],
    /// Normalised quaternion and the norm it was divided by.
    qn: [R; 4],
    qnorm: R,
    rq: [[R; 3]; 3],
    scale: [R; 3],
    /// Covariance in camera space.
    cov_cam: [[R; 3]; 3],
    /// Jacobian point after the field-of-view clamp, and which axes were clamped.
    tx: R,
    ty: R,
    clamped_x: bool,
    clamped_y: bool,
    jac: [[R; 3]; 2],
    /// Dilated 2D covariance (a, b, c).
    cov2d: [R; 3],
}

#[inline(always)]
fn geometry<R: Real>(p: &Params<'_, R>, i: usize, cam: &CameraR<R>) -> Option<Geometry<R>> {
    let m = [p.means[3 * i], p.means[3 * i + 1], p.means[3 * i + 2]];
    let r = &cam.rot;
    let mut pc = [R::ZERO; 3];
    for a in 0..3 {
        pc[a] = r[a][0] * m[0] + r[a][1] * m[1] + r[a][2] * m[2] + cam.trans[a];
    }
    let z = pc[2];
    // `!(z > near)` also rejects NaN.
    if !(z > c(NEAR_PLANE)) || !pc[0].is_finite() || !pc[1].is_finite() || !z.is_finite() {
        return None;
    }
    let q = [
        p.quats[4 * i],
        p.quats[4 * i + 1],
        p.quats[4 * i + 2],
        p.quats[4 * i + 3],
    ];
    let qnorm = (q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]).sqrt();
    if !(qnorm > R::ZERO) || !qnorm.is_finite() {
        return None;
    }
    let qn = q.map(|v| v / qnorm);
    let rq = quat_to_rot(qn);
    let ls = &p.log_scales[3 * i..3 * i + 3];
    let scale = [ls[0].exp(), ls[1].exp(), ls[2].exp()];
    // Σ = M Mᵀ, M = Rq diag(s).
    let mut mm = rq;
    for row in mm.iter_mut() {
        for (v, s) in row.iter_mut().zip(scale) {
            *v *= s;
        }
    }
    let sigma = matmul3(&mm, &transpose3(&mm));
    let cov_cam = matmul3(&matmul3(r, &sigma), &transpose3(r));

    let u = pc[0] / z;
    let v = pc[1] / z;
    let ux = u.max(-cam.lim_x.0).min(cam.lim_x.1);
    let vy = v.max(-cam.lim_y.0).min(cam.lim_y.1);
    let clamped_x = u < -cam.lim_x.0 || u > cam.lim_x.1;
    let clamped_y = v < -cam.lim_y.0 || v > cam.lim_y.1;
    let tx = if clamped_x { z * ux } else { pc[0] };
    let ty = if clamped_y { z * vy } else { pc[1] };
    let z2 = z * z;
    let jac = [
        [cam.fx / z, R::ZERO, -cam.fx * tx / z2],
        [R::ZERO, cam.fy / z, -cam.fy * ty / z2],
    ];
    // S = J Σc Jᵀ (2x2, symmetric).
    let mut jc = [[R::ZERO; 3]; 2];
    for a in 0..2 {
        for b in 0..3 {
            jc[a][b] =
                jac[a][0] * cov_cam[0][b] + jac[a][1] * cov_cam[1][b] + jac[a][2] * cov_cam[2][b];
        }
    }
    let s = |a: usize, b: usize| jc[a][0] * jac[b][0] + jc[a][1] * jac[b][1] + jc[a][2] * jac[b][2];
    let cov2d = [s(0, 0) + c(LOW_PASS), s(0, 1), s(1, 1) + c(LOW_PASS)];
    Some(Geometry {
        pc,
        qn,
        qnorm,
        rq,
        scale,
        cov_cam,
        tx,
        ty,
        clamped_x,
        clamped_y,
        jac,
        cov2d,
    })
}

/// Projects Gaussian `i`. Returns a culled splat (`radius == 0`) when it is behind the near plane,
/// degenerate, off screen or non-finite. Colours are computed only when `with_color` is set.
#[inline(always)]
pub fn project_one<R: Real>(
    p: &Params<'_, R>,
    i: usize,
    cam: &CameraR<R>,
    with_color: bool,
) -> Splat<R> {
    match project_geometry(p, i, cam) {
        Some(shape) => project_appearance(p, i, cam, &shape.splat, shape.cov_diag, with_color),
        None => Splat::default(),
    }
}

/// The part of a projection that depends only on the mean, scales and rotation (and the camera): a
/// splat with its mean, conic, depth, radius and tiles set, and the 2D covariance's diagonal the
/// opacity-dependent extents need. Fits that change appearance only reuse it across steps.
#[derive(Clone, Copy, Debug)]
pub struct SplatShape<R> {
    pub splat: Splat<R>,
    /// Diagonal (a, c) of the dilated 2D covariance.
    pub cov_diag: [R; 2],
}

/// The geometry of the projection of Gaussian `i`; `None` where [`project_one`] culls it for reasons
/// of geometry (behind the near plane, degenerate, off screen, non-finite).
#[inline(always)]
pub fn project_geometry<R: Real>(
    p: &Params<'_, R>,
    i: usize,
    cam: &CameraR<R>,
) -> Option<SplatShape<R>> {
    let g = geometry(p, i, cam)?;
    let [a, b, cc] = g.cov2d;
    let det = a * cc - b * b;
    if !(det > R::ZERO) || !det.is_finite() {
        return None;
    }
    let conic = [cc / det, -b / det, a / det];
    let z = g.pc[2];
    let mean = [cam.fx * g.pc[0] / z + cam.cx, cam.fy * g.pc[1] / z + cam.cy];
    let mid = c::<R>(0.5) * (a + cc);
    let lambda = mid + (mid * mid - det).max(c(0.1)).sqrt();
    let radius_f = (c::<R>(3.0) * lambda.sqrt()).ceil();
    if !radius_f.is_finite() || !mean[0].is_finite() || !mean[1].is_finite() {
        return None;
    }
    let radius = radius_f.to_f64().min(1e9) as u32;
    let (tiles_x, tiles_y) = cam.tiles();
    let tile = c::<R>(TILE as f64);
    let clamp_tile = |v: R, hi: u32| -> u32 { v.max(R::ZERO).min(c(hi as f64)).to_f64() as u32 };
    let x0 = clamp_tile(((mean[0] - radius_f) / tile).floor(), tiles_x);
    let x1 = clamp_tile(((mean[0] + radius_f) / tile).ceil(), tiles_x);
    let y0 = clamp_tile(((mean[1] - radius_f) / tile).floor(), tiles_y);
    let y1 = clamp_tile(((mean[1] + radius_f) / tile).ceil(), tiles_y);
    if radius == 0 || x1 <= x0 || y1 <= y0 {
        return None;
    }
    Some(SplatShape {
        splat: Splat {
            mean,
            conic,
            depth: z,
            radius,
            tiles: [x0, y0, x1, y1].map(|t| t as u16),
            ..Splat::default()
        },
        cov_diag: [a, cc],
    })
}

/// Completes the projection of Gaussian `i` from its [`project_geometry`] (`shape` and `cov_diag`):
/// opacity, the extents where its alpha can reach 1/255, and (with `with_color`) its colour. Culled when
/// the opacity is NaN.
#[inline(always)]
pub fn project_appearance<R: Real>(
    p: &Params<'_, R>,
    i: usize,
    cam: &CameraR<R>,
    shape: &Splat<R>,
    cov_diag: [R; 2],
    with_color: bool,
) -> Splat<R> {
    let opacity = sigmoid(p.opacity_logits[i]);
    if opacity.is_nan() {
        return Splat::default();
    }
    let [a, cc] = cov_diag;
    // alpha = o·exp(-σ) ≥ 1/255  ⇔  σ ≤ ln(255·o). Enlarged a little so float rounding in the per-pixel
    // test can never accept a pixel this bound rejects.
    let sm = (opacity / c(ALPHA_MIN)).ln();
    let sigma_max = if sm >= R::ZERO {
        sm * c(1.0 + 1e-4) + c(1e-4)
    } else {
        sm
    };
    let (half_width, half_height) = if sigma_max >= R::ZERO {
        (
            (c::<R>(2.0) * sigma_max * a).sqrt(),
            (c::<R>(2.0) * sigma_max * cc).sqrt(),
        )
    } else {
        (R::ZERO, R::ZERO)
    };
    let mut splat = Splat {
        opacity,
        half_height,
        half_width,
        ..*shape
    };
    if with_color {
        let (color, clamped) = eval_color(p, i, cam);
        splat.color = color;
        splat.clamped = clamped;
    }
    splat
}

/// Unit direction from the camera centre to the mean, and the length it was divided by.
#[inline(always)]
fn view_dir<R: Real>(p: &Params<'_, R>, i: usize, cam: &CameraR<R>) -> ([R; 3], R) {
    let d = [
        p.means[3 * i] - cam.center[0],
        p.means[3 * i + 1] - cam.center[1],
        p.means[3 * i + 2] - cam.center[2],
    ];
    let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    if n > R::ZERO {
        (d.map(|v| v / n), n)
    } else {
        ([R::ZERO; 3], R::ONE)
    }
}

#[inline(always)]
fn eval_color<R: Real>(p: &Params<'_, R>, i: usize, cam: &CameraR<R>) -> ([R; 3], u8) {
    let k = super::sh_coeffs_of(p.sh_degree);
    let coeffs = &p.sh[i * k * 3..(i + 1) * k * 3];
    let (dir, _) = view_dir(p, i, cam);
    let mut basis = [R::ZERO; sh::MAX_COEFFS];
    sh::basis(p.sh_degree, dir, &mut basis);
    let mut color = [c::<R>(0.5); 3];
    for (kk, b) in basis.iter().take(k).enumerate() {
        for (ch, col) in color.iter_mut().enumerate() {
            *col += *b * coeffs[kk * 3 + ch];
        }
    }
    let mut clamped = 0u8;
    for (ch, col) in color.iter_mut().enumerate() {
        if *col < R::ZERO {
            *col = R::ZERO;
            clamped |= 1 << ch;
        }
    }
    (color, clamped)
}

/// Gradients of the loss with respect to the projected quantities of one Gaussian.
#[derive(Clone, Copy, Debug, Default)]
pub struct SplatGrad<R> {
    pub mean: [R; 2],
    pub conic: [R; 3],
    pub opacity: R,
    pub color: [R; 3],
    pub depth: R,
}

impl<R: Real> SplatGrad<R> {
    /// Whether every entry is exactly zero (the Gaussian did not contribute to any pixel).
    #[inline]
    pub fn is_zero(&self) -> bool {
        let z = R::ZERO;
        self.mean == [z; 2]
            && self.conic == [z; 3]
            && self.opacity == z
            && self.color == [z; 3]
            && self.depth == z
    }
}

/// Backward of [`project_appearance`] for Gaussian `i`: overwrites `opacity_logit` and `sh` with their
/// gradients; `sh` must be zero on entry. Returns the gradient the colour sends to the mean (through the
/// view direction), which fits with frozen geometry drop.
#[inline(always)]
pub fn appearance_backward<R: Real>(
    p: &Params<'_, R>,
    i: usize,
    cam: &CameraR<R>,
    splat: &Splat<R>,
    v: &SplatGrad<R>,
    opacity_logit: &mut R,
    sh: &mut [R],
) -> [R; 3] {
    // Opacity: o = sigmoid(logit).
    let o = splat.opacity;
    *opacity_logit = v.opacity * o * (R::ONE - o);

    // Colour: SH coefficients and the view direction.
    let mut v_mean = [R::ZERO; 3];
    let mut v_col = v.color;
    for (ch, vc) in v_col.iter_mut().enumerate() {
        if splat.clamped & (1 << ch) != 0 {
            *vc = R::ZERO;
        }
    }
    if v_col.iter().any(|&x| x != R::ZERO) {
        let k = super::sh_coeffs_of(p.sh_degree);
        let coeffs = &p.sh[i * k * 3..(i + 1) * k * 3];
        let (dir, dir_len) = view_dir(p, i, cam);
        let mut basis = [R::ZERO; sh::MAX_COEFFS];
        sh::basis(p.sh_degree, dir, &mut basis);
        let mut v_basis = [R::ZERO; sh::MAX_COEFFS];
        for kk in 0..k {
            for ch in 0..3 {
                sh[kk * 3 + ch] = basis[kk] * v_col[ch];
                v_basis[kk] += coeffs[kk * 3 + ch] * v_col[ch];
            }
        }
        let v_dir = sh::basis_vjp(p.sh_degree, dir, &v_basis);
        // Through the normalisation d = raw/|raw|.
        let dot = dir[0] * v_dir[0] + dir[1] * v_dir[1] + dir[2] * v_dir[2];
        for a in 0..3 {
            v_mean[a] += (v_dir[a] - dir[a] * dot) / dir_len;
        }
    }
    v_mean
}

/// Gradients of one Gaussian's parameters, written into the given slices (same layouts as the scene).
pub struct ParamGradsMut<'a, R> {
    pub mean: &'a mut [R],
    pub log_scale: &'a mut [R],
    pub quat: &'a mut [R],
    pub opacity_logit: &'a mut R,
    pub sh: &'a mut [R],
}

/// Backward of [`project_one`] for Gaussian `i`: overwrites `out` with the parameter gradients.
#[inline(always)]
pub fn project_one_backward<R: Real>(
    p: &Params<'_, R>,
    i: usize,
    cam: &CameraR<R>,
    splat: &Splat<R>,
    v: &SplatGrad<R>,
    out: ParamGradsMut<'_, R>,
) {
    out.mean.fill(R::ZERO);
    out.log_scale.fill(R::ZERO);
    out.quat.fill(R::ZERO);
    *out.opacity_logit = R::ZERO;
    out.sh.fill(R::ZERO);
    if splat.radius == 0 {
        return;
    }
    let Some(g) = geometry(p, i, cam) else {
        return;
    };
    let two: R = c(2.0);
    let mut v_mean = appearance_backward(p, i, cam, splat, v, out.opacity_logit, out.sh);

    // Conic = S⁻¹ → gradient of S: V_S = -P G P with G the symmetric matrix of the conic gradient
    // (the off-diagonal conic entry stands for both off-diagonal elements).
    let pm = [
        [splat.conic[0], splat.conic[1]],
        [splat.conic[1], splat.conic[2]],
    ];
    let half: R = c(0.5);
    let gm = [
        [v.conic[0], half * v.conic[1]],
        [half * v.conic[1], v.conic[2]],
    ];
    let mut pg = [[R::ZERO; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            pg[a][b] = pm[a][0] * gm[0][b] + pm[a][1] * gm[1][b];
        }
    }
    let mut vs = [[R::ZERO; 2]; 2];
    for a in 0..2 {
        for b in 0..2 {
            vs[a][b] = -(pg[a][0] * pm[0][b] + pg[a][1] * pm[1][b]);
        }
    }

    // S = J Σc Jᵀ + 0.3 I  →  V_Σc = Jᵀ V_S J,  V_J = 2 V_S J Σc.
    let jac = &g.jac;
    let mut vs_j = [[R::ZERO; 3]; 2];
    for a in 0..2 {
        for b in 0..3 {
            vs_j[a][b] = vs[a][0] * jac[0][b] + vs[a][1] * jac[1][b];
        }
    }
    let mut v_cov_cam = [[R::ZERO; 3]; 3];
    for a in 0..3 {
        for b in 0..3 {
            v_cov_cam[a][b] = jac[0][a] * vs_j[0][b] + jac[1][a] * vs_j[1][b];
        }
    }
    let mut v_jac = [[R::ZERO; 3]; 2];
    for a in 0..2 {
        for b in 0..3 {
            v_jac[a][b] = two
                * (vs_j[a][0] * g.cov_cam[0][b]
                    + vs_j[a][1] * g.cov_cam[1][b]
                    + vs_j[a][2] * g.cov_cam[2][b]);
        }
    }

    // Jacobian entries depend on z and the clamped (tx, ty).
    let [x, y, z] = g.pc;
    let (fx, fy) = (cam.fx, cam.fy);
    let z2 = z * z;
    let z3 = z2 * z;
    let mut v_pc = [R::ZERO; 3];
    v_pc[2] += -fx / z2 * v_jac[0][0] - fy / z2 * v_jac[1][1]
        + two * fx * g.tx / z3 * v_jac[0][2]
        + two * fy * g.ty / z3 * v_jac[1][2];
    let v_tx = -fx / z2 * v_jac[0][2];
    let v_ty = -fy / z2 * v_jac[1][2];
    // tx = x when not clamped, else z·limit.
    if g.clamped_x {
        v_pc[2] += v_tx * (g.tx / z);
    } else {
        v_pc[0] += v_tx;
    }
    if g.clamped_y {
        v_pc[2] += v_ty * (g.ty / z);
    } else {
        v_pc[1] += v_ty;
    }
    // Projected mean and depth.
    v_pc[0] += fx / z * v.mean[0];
    v_pc[1] += fy / z * v.mean[1];
    v_pc[2] += -fx * x / z2 * v.mean[0] - fy * y / z2 * v.mean[1] + v.depth;

    // p = R m + t.
    let r = &cam.rot;
    for a in 0..3 {
        v_mean[a] += r[0][a] * v_pc[0] + r[1][a] * v_pc[1] + r[2][a] * v_pc[2];
    }
    out.mean.copy_from_slice(&v_mean);

    // Σc = R Σ Rᵀ → V_Σ = Rᵀ V_Σc R; Σ = M Mᵀ → V_M = 2 V_Σ M.
    let v_sigma = matmul3(&matmul3(&transpose3(r), &v_cov_cam), r);
    let mut mm = g.rq;
    for row in mm.iter_mut() {
        for (val, s) in row.iter_mut().zip(g.scale) {
            *val *= s;
        }
    }
    let v_m = matmul3(&v_sigma, &mm).map(|row| row.map(|val| two * val));
    // M = Rq diag(s).
    let mut v_rq = [[R::ZERO; 3]; 3];
    let mut v_s = [R::ZERO; 3];
    for a in 0..3 {
        for b in 0..3 {
            v_rq[a][b] = v_m[a][b] * g.scale[b];
            v_s[b] += v_m[a][b] * g.rq[a][b];
        }
    }
    for b in 0..3 {
        out.log_scale[b] = v_s[b] * g.scale[b];
    }
    let v_qn = quat_to_rot_vjp(g.qn, &v_rq);
    let dot = (0..4).fold(R::ZERO, |acc, a| acc + g.qn[a] * v_qn[a]);
    for a in 0..4 {
        out.quat[a] = (v_qn[a] - g.qn[a] * dot) / g.qnorm;
    }
}
