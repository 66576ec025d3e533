//! Reductions across the units of one cube, shared by the splatting and the network kernels.

use cubecl::prelude::*;

/// Largest `v` over the cube's `units` units (a power of two); every unit gets the result. Every unit of
/// the cube must call it (it synchronises the cube).
#[cube]
pub fn cube_max<N: Numeric>(v: N, #[comptime] units: u32) -> N {
    cube_reduce::<N>(v, units, true)
}

/// Sum of `v` over the cube's `units` units (a power of two); every unit gets the total. Every unit of
/// the cube must call it.
#[cube]
pub fn cube_sum<N: Numeric>(v: N, #[comptime] units: u32) -> N {
    cube_reduce::<N>(v, units, false)
}

/// A shared-memory tree over the cube's units: the maximum (`max`) or the sum.
#[cube]
fn cube_reduce<N: Numeric>(v: N, #[comptime] units: u32, #[comptime] max: bool) -> N {
    let mut s = Shared::<[N]>::new_slice(comptime!(units as usize));
    s[UNIT_POS as usize] = v;
    sync_cube();
    let mut stride = comptime!(units / 2).runtime();
    #[unroll]
    for _ in 0..comptime!(units.trailing_zeros()) {
        if UNIT_POS < stride {
            let other = s[(UNIT_POS + stride) as usize];
            if comptime!(max) {
                if other > s[UNIT_POS as usize] {
                    s[UNIT_POS as usize] = other;
                }
            } else {
                s[UNIT_POS as usize] += other;
            }
        }
        sync_cube();
        stride /= 2;
    }
    let total = s[0];
    sync_cube();
    total
}
