//! Hand-written AVX2+FMA versions of the rasteriser's 8-pixel segment kernels for `f32`.
//!
//! They compute exactly what the portable kernels in `raster.rs`/`raster_backward.rs` compute (same
//! formulas, same tests), only with fused multiply-adds and direct lane masks instead of what the
//! auto-vectoriser makes of bit manipulations. Forward and backward both use [`alpha_lanes`], so their
//! skip decisions agree bit for bit. Only called from code compiled for AVX2+FMA after a run-time check.

#![cfg(target_arch = "x86_64")]

use super::project::{Splat, ALPHA_MAX, ALPHA_MIN, T_MIN};
use super::segment::{LaneGrads, SegState, SegTemps, SEG};
use std::arch::x86_64::*;

const LANE_BITS: [i32; SEG] = [1, 2, 4, 8, 16, 32, 64, 128];

/// All-ones lanes where bit `l` of `bits` is set.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn lane_mask(bits: u32) -> __m256 {
    let b = _mm256_set1_epi32(bits as i32);
    let lb = _mm256_loadu_si256(LANE_BITS.as_ptr() as *const __m256i);
    _mm256_castsi256_ps(_mm256_cmpeq_epi32(_mm256_and_si256(b, lb), lb))
}

/// e^x with the algorithm of `Real::exp_fast` for f32 (2^n · Taylor polynomial of degree 6).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn exp(x: __m256) -> __m256 {
    const ROUND: f32 = 12_582_912.0;
    let x = _mm256_min_ps(
        _mm256_max_ps(x, _mm256_set1_ps(-87.0)),
        _mm256_set1_ps(88.0),
    );
    let shifted = _mm256_fmadd_ps(
        x,
        _mm256_set1_ps(std::f32::consts::LOG2_E),
        _mm256_set1_ps(ROUND),
    );
    let n = _mm256_sub_ps(shifted, _mm256_set1_ps(ROUND));
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(0.693_359_4), x);
    let r = _mm256_fnmadd_ps(n, _mm256_set1_ps(-2.121_944_4e-4), r);
    let mut p = _mm256_set1_ps(1.0 / 720.0);
    for coef in [1.0 / 120.0, 1.0 / 24.0, 1.0 / 6.0, 0.5, 1.0, 1.0] {
        p = _mm256_fmadd_ps(p, r, _mm256_set1_ps(coef));
    }
    let ni = _mm256_sub_epi32(
        _mm256_castps_si256(shifted),
        _mm256_set1_epi32(ROUND.to_bits() as i32),
    );
    let scale = _mm256_castsi256_ps(_mm256_slli_epi32(
        _mm256_add_epi32(ni, _mm256_set1_epi32(127)),
        23,
    ));
    _mm256_mul_ps(p, scale)
}

/// Per lane: dx = mean_x − x, σ, exp(−σ) and alpha = min(0.99, o·exp(−σ)).
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn alpha_lanes(s: &Splat<f32>, dy: f32, xs: &[f32; SEG]) -> [__m256; 4] {
    let [a, b, c] = s.conic;
    let dx = _mm256_sub_ps(_mm256_set1_ps(s.mean[0]), _mm256_loadu_ps(xs.as_ptr()));
    // σ = ½(a dx² + c dy²) + b dy dx
    let quad = _mm256_fmadd_ps(
        _mm256_mul_ps(_mm256_set1_ps(a), dx),
        dx,
        _mm256_set1_ps(c * dy * dy),
    );
    let sigma = _mm256_fmadd_ps(
        _mm256_set1_ps(b * dy),
        dx,
        _mm256_mul_ps(_mm256_set1_ps(0.5), quad),
    );
    let vis = exp(_mm256_sub_ps(_mm256_setzero_ps(), sigma));
    let alpha = _mm256_min_ps(
        _mm256_mul_ps(_mm256_set1_ps(s.opacity), vis),
        _mm256_set1_ps(ALPHA_MAX as f32),
    );
    [dx, sigma, vis, alpha]
}

/// Lanes that pass the alpha tests among `allowed`.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn valid_lanes(allowed: u32, sigma: __m256, alpha: __m256) -> __m256 {
    let ok_sigma = _mm256_cmp_ps::<_CMP_GE_OQ>(sigma, _mm256_setzero_ps());
    let ok_alpha = _mm256_cmp_ps::<_CMP_GE_OQ>(alpha, _mm256_set1_ps(ALPHA_MIN as f32));
    _mm256_and_ps(lane_mask(allowed), _mm256_and_ps(ok_sigma, ok_alpha))
}

/// Forward step of one Gaussian over one segment; see `raster::forward_segment`.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub unsafe fn forward_segment(
    s: &Splat<f32>,
    dy: f32,
    xs: &[f32; SEG],
    trans: &mut [f32; SEG],
    live: u32,
    w: &mut [f32; SEG],
) -> (u32, u32) {
    let [_, sigma, _, alpha] = alpha_lanes(s, dy, xs);
    let valid = valid_lanes(live, sigma, alpha);
    let t = _mm256_loadu_ps(trans.as_ptr());
    let next = _mm256_mul_ps(t, _mm256_sub_ps(_mm256_set1_ps(1.0), alpha));
    let stop = _mm256_and_ps(
        valid,
        _mm256_cmp_ps::<_CMP_LT_OQ>(next, _mm256_set1_ps(T_MIN as f32)),
    );
    let hit = _mm256_andnot_ps(stop, valid);
    _mm256_storeu_ps(w.as_mut_ptr(), _mm256_and_ps(hit, _mm256_mul_ps(alpha, t)));
    _mm256_storeu_ps(trans.as_mut_ptr(), _mm256_blendv_ps(t, next, hit));
    (
        _mm256_movemask_ps(hit) as u32,
        _mm256_movemask_ps(stop) as u32,
    )
}

#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn ld(v: &[f32; SEG]) -> __m256 {
    _mm256_loadu_ps(v.as_ptr())
}

#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn st(v: &mut [f32; SEG], x: __m256) {
    _mm256_storeu_ps(v.as_mut_ptr(), x)
}

/// v ← a·b + v.
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn fma_into(v: &mut [f32; SEG], a: __m256, b: __m256) {
    let cur = ld(v);
    st(v, _mm256_fmadd_ps(a, b, cur));
}

/// Backward pass 1; see `raster_backward::pass1`.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub unsafe fn backward_pass1(
    s: &Splat<f32>,
    dy: f32,
    xs: &[f32; SEG],
    active: u32,
    st8: &SegState<'_, f32>,
    tmp: &mut SegTemps<f32>,
) -> u32 {
    let [dx, sigma, vis, alpha] = alpha_lanes(s, dy, xs);
    let act = valid_lanes(active, sigma, alpha);
    let one = _mm256_set1_ps(1.0);
    let ra = _mm256_div_ps(one, _mm256_sub_ps(one, alpha));
    let t_new = _mm256_mul_ps(ld(st8.trans), ra);
    // dL/dalpha = Σ_ch (c·T − behind·ra)·v_ch + (z·T − behind_z·ra)·v_z + T_final·ra·dL/dT_final
    let mut va = _mm256_mul_ps(ld(st8.v_final), ra);
    for ch in 0..3 {
        let term = _mm256_fmsub_ps(
            _mm256_set1_ps(s.color[ch]),
            t_new,
            _mm256_mul_ps(ld(st8.behind[ch]), ra),
        );
        va = _mm256_fmadd_ps(term, ld(st8.v_color[ch]), va);
    }
    let term = _mm256_fmsub_ps(
        _mm256_set1_ps(s.depth),
        t_new,
        _mm256_mul_ps(ld(st8.behind[3]), ra),
    );
    va = _mm256_fmadd_ps(term, ld(st8.v_depth), va);
    st(&mut tmp.dx, dx);
    st(&mut tmp.vis, vis);
    st(&mut tmp.alpha, alpha);
    st(&mut tmp.ra, ra);
    st(&mut tmp.t_new, t_new);
    st(&mut tmp.v_alpha, va);
    _mm256_movemask_ps(act) as u32
}

/// Backward pass 3; see `raster_backward::pass3`.
#[target_feature(enable = "avx2,fma")]
#[inline]
pub unsafe fn backward_pass3(
    s: &Splat<f32>,
    dy: f32,
    act_bits: u32,
    st8: &mut SegState<'_, f32>,
    tmp: &SegTemps<f32>,
    lg: &mut LaneGrads<f32>,
) {
    let act = lane_mask(act_bits);
    let t_new = ld(&tmp.t_new);
    let fac = _mm256_and_ps(act, _mm256_mul_ps(ld(&tmp.alpha), t_new));
    st(st8.trans, _mm256_blendv_ps(ld(st8.trans), t_new, act));
    for ch in 0..3 {
        fma_into(st8.behind[ch], _mm256_set1_ps(s.color[ch]), fac);
        fma_into(&mut lg.color[ch], fac, ld(st8.v_color[ch]));
    }
    fma_into(st8.behind[3], _mm256_set1_ps(s.depth), fac);
    fma_into(&mut lg.depth, fac, ld(st8.v_depth));
    // Where alpha was clamped at 0.99 it depends on neither σ nor the opacity.
    let vis = ld(&tmp.vis);
    let raw = _mm256_mul_ps(_mm256_set1_ps(s.opacity), vis);
    let free = _mm256_and_ps(
        act,
        _mm256_cmp_ps::<_CMP_LE_OQ>(raw, _mm256_set1_ps(ALPHA_MAX as f32)),
    );
    let va = ld(&tmp.v_alpha);
    let v_sigma = _mm256_and_ps(
        free,
        _mm256_sub_ps(_mm256_setzero_ps(), _mm256_mul_ps(raw, va)),
    );
    let dx = ld(&tmp.dx);
    let [a, b, c] = s.conic;
    let sdx = _mm256_mul_ps(v_sigma, dx);
    fma_into(&mut lg.conic[0], sdx, dx);
    fma_into(&mut lg.conic[1], sdx, _mm256_set1_ps(dy));
    fma_into(&mut lg.conic[2], v_sigma, _mm256_set1_ps(dy * dy));
    let gx = _mm256_fmadd_ps(_mm256_set1_ps(a), dx, _mm256_set1_ps(b * dy));
    let gy = _mm256_fmadd_ps(_mm256_set1_ps(b), dx, _mm256_set1_ps(c * dy));
    fma_into(&mut lg.mean[0], v_sigma, gx);
    fma_into(&mut lg.mean[1], v_sigma, gy);
    let cur = ld(&lg.opacity);
    st(
        &mut lg.opacity,
        _mm256_add_ps(cur, _mm256_and_ps(free, _mm256_mul_ps(vis, va))),
    );
}
