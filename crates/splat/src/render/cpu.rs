//! What the renderer's CPU stages need to know about the CPU: whether it has AVX2+FMA, and one way to run
//! a piece of work in the form compiled for it ([`dispatch`]). Every stage (projection, compositing,
//! their backward passes, lifting) goes through here, so a portable build or a test that forces the
//! portable path changes all of them at once.

/// Set by tests to compare the portable kernels with the AVX2 ones on the same machine.
static FORCE_PORTABLE: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// Makes [`has_avx2`] report false (or restores detection).
#[cfg(test)]
pub(crate) fn force_portable(on: bool) {
    FORCE_PORTABLE.store(on, std::sync::atomic::Ordering::SeqCst);
}

/// Whether the CPU has AVX2 and FMA (checked once; the hot loops are compiled for it as well).
#[inline]
pub(crate) fn has_avx2() -> bool {
    if FORCE_PORTABLE.load(std::sync::atomic::Ordering::Relaxed) {
        return false;
    }
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Whether `R` is `f32` (decided at compile time after monomorphisation): the hand-written AVX2 kernels
/// exist for `f32` only.
#[inline(always)]
pub(crate) fn is_f32<R: 'static>() -> bool {
    std::any::TypeId::of::<R>() == std::any::TypeId::of::<f32>()
}

/// Hints the CPU to start loading `v` into cache.
#[inline(always)]
pub(crate) fn prefetch<T>(v: &T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: prefetching is a hint without side effects; the address comes from a valid reference.
    unsafe {
        std::arch::x86_64::_mm_prefetch(v as *const T as *const i8, std::arch::x86_64::_MM_HINT_T0);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = v;
}

/// Work that is compiled twice, portable and for AVX2+FMA; [`dispatch`] runs the form the CPU supports.
pub(crate) trait Kernel {
    type Output;

    /// The work itself. `SIMD` is set in the copy compiled for AVX2+FMA, where the `f32` kernels of
    /// `simd.rs` may be called. Implementations should be `#[inline(always)]`, so the body is compiled into
    /// each copy.
    fn run<const SIMD: bool>(self) -> Self::Output;
}

/// Runs `kernel` compiled for AVX2+FMA when the CPU has them, portably otherwise.
#[inline(always)]
pub(crate) fn dispatch<K: Kernel>(kernel: K) -> K::Output {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU supports the features `run_avx2` is compiled for.
        return unsafe { run_avx2(kernel) };
    }
    kernel.run::<false>()
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn run_avx2<K: Kernel>(kernel: K) -> K::Output {
    kernel.run::<true>()
}
