//! Process-wide settings for the binaries.

/// Makes glibc's allocator keep large blocks in the heap instead of `mmap`ing and unmapping them per
/// allocation. UNet activations at batch 6 are 30–250 MB each, a render's per-Gaussian and per-pixel
/// buffers tens of MB; with glibc's defaults each is a fresh mapping that the kernel must fault in and zero
/// (about 13% of a batch-6 SD 1.5 forward; 40–90 % of the projection stages of a 125k-Gaussian render,
/// depending on what the process allocated before, since glibc adapts its threshold). After this call
/// freed memory is reused instead (the process keeps its peak heap until exit, which suits a CLI).
/// Process-wide; a no-op on other platforms. Call once at startup, before heavy work.
pub fn tune_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        extern "C" {
            fn mallopt(param: i32, value: i32) -> i32;
        }
        const M_TRIM_THRESHOLD: i32 = -1;
        const M_TOP_PAD: i32 = -2;
        const M_MMAP_MAX: i32 = -4;
        // SAFETY: mallopt only changes allocator tuning parameters; these values are valid for glibc.
        unsafe {
            mallopt(M_MMAP_MAX, 0);
            mallopt(M_TRIM_THRESHOLD, i32::MAX);
            mallopt(M_TOP_PAD, 256 << 20);
        }
    }
}
