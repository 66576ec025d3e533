//! Reductions across the units of one cube, shared by the splatting and the network kernels.

use cubecl::prelude::*;

/// Largest `v` over the cube's `units` units (a power of two), through a shared-memory tree; every unit
/// gets the result. Every unit of the cube must call it (it synchronises the cube).
#[cube]
pub fn cube_max<N: Numeric>(v: N, #[comptime] units: u32) -> N {
    let mut s = Shared::<[N]>::new_slice(comptime!(units as usize));
    s[UNIT_POS as usize] = v;
    sync_cube();
    let mut stride = comptime!(units / 2).runtime();
    #[unroll]
    for _ in 0..comptime!(units.trailing_zeros()) {
        if UNIT_POS < stride {
            let other = s[(UNIT_POS + stride) as usize];
            if other > s[UNIT_POS as usize] {
                s[UNIT_POS as usize] = other;
            }
        }
        sync_cube();
        stride /= 2;
    }
    let total = s[0];
    sync_cube();
    total
}
