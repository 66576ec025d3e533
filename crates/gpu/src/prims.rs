//! Device-wide building blocks the renderer needs and CubeCL 0.11 does not ship: fills, an exclusive
//! prefix sum and a stable LSD radix sort of (u32 key, u32 value) pairs.
//!
//! Both the scan and the sort work on chunks walked sequentially by one unit each: no shared memory and
//! no barriers (barriers cost ~10x on software Vulkan), stability for free, and enough units for a GPU
//! once the arrays are large (the chunk length grows with the array so the unit count stays ~16k).

use cubecl::client::Client;
use cubecl::prelude::*;
use cubecl::server::Handle;

use crate::{server_error, GpuError};

/// Units per cube of the 1-D launches here.
pub const BLOCK: u32 = 256;
/// Arrays up to this long are scanned by one cube ([`scan_block`]); longer ones in chunks first.
const BLOCK_SCAN_MAX: usize = 2048;
/// Sort digits are this many bits wide (16 buckets).
const RADIX_BITS: u32 = 4;
const RADIX: u32 = 1 << RADIX_BITS;

/// Cube count and dimension covering `n` units, spread over two dimensions beyond 65535 cubes (kernels
/// use `ABSOLUTE_POS`, which is linear over the whole grid, and check it against their length).
pub fn grid(n: usize) -> (CubeCount, CubeDim) {
    let cubes = (n.max(1) as u32).div_ceil(BLOCK);
    let count = if cubes <= 65535 {
        CubeCount::new_1d(cubes)
    } else {
        CubeCount::new_2d(65535, cubes.div_ceil(65535))
    };
    (count, CubeDim::new_1d(BLOCK))
}

/// A buffer argument of `len` elements. The handle must hold at least that many.
pub fn arg(h: &Handle, len: usize) -> BufferArg {
    // SAFETY: every caller passes the element count it allocated the handle with (or fewer).
    unsafe { BufferArg::from_raw_parts(h.clone(), len.max(1)) }
}

/// A device buffer of `n` f32 or u32 values (uninitialised; at least 4 bytes).
pub fn empty32(client: &Client, n: usize) -> Handle {
    client.empty(4 * n.max(1))
}

/// Uploads f32 values.
pub fn upload_f32(client: &Client, v: &[f32]) -> Handle {
    if v.is_empty() {
        return empty32(client, 1);
    }
    client.create_from_slice(f32::as_bytes(v))
}

/// Uploads u32 values.
pub fn upload_u32(client: &Client, v: &[u32]) -> Handle {
    if v.is_empty() {
        return empty32(client, 1);
    }
    client.create_from_slice(u32::as_bytes(v))
}

/// How many reads [`read_f32`] / [`read_u32`] / [`read_raw`] made in this process so far, and how long
/// the host waited in them (a read waits for all work queued before it, so this is the time the host
/// stood still while the device caught up; the difference over a span of work says whether it is bound
/// by the device or by the host's launching). Their bytes: [`crate::traffic::DeviceTraffic`].
pub fn read_waits() -> (u64, std::time::Duration) {
    crate::traffic::read_waits()
}

/// The bytes of `h`'s buffer, read back (counted in [`read_waits`] and the process's
/// [`crate::traffic::DeviceTraffic`]): the read every engine's read-back goes through.
pub fn read_raw(client: &Client, h: &Handle) -> Result<cubecl::bytes::Bytes, GpuError> {
    let bytes = h.size_in_used() as usize;
    crate::traffic::counted_read(bytes, || client.read_one(h.clone())).map_err(server_error)
}

/// Reads `n` f32 values back (this waits for the work that writes them).
pub fn read_f32(client: &Client, h: &Handle, n: usize) -> Result<Vec<f32>, GpuError> {
    if n == 0 {
        return Ok(vec![]);
    }
    let bytes = read_raw(client, h)?;
    Ok(f32::from_bytes(&bytes)[..n].to_vec())
}

/// Reads `n` u32 values back.
pub fn read_u32(client: &Client, h: &Handle, n: usize) -> Result<Vec<u32>, GpuError> {
    if n == 0 {
        return Ok(vec![]);
    }
    let bytes = read_raw(client, h)?;
    Ok(u32::from_bytes(&bytes)[..n].to_vec())
}

#[cube(launch)]
fn fill_u32(out: &mut [u32], n: u32, value: u32) {
    if (ABSOLUTE_POS as u32) < n {
        out[ABSOLUTE_POS] = value;
    }
}

/// A buffer of `n` 32-bit zeros (as f32 0.0 or u32 0).
pub fn zeros32(client: &Client, n: usize) -> Handle {
    let h = empty32(client, n);
    fill32(client, &h, n, 0);
    h
}

/// Sets the first `n` 32-bit words of `h` to `bits`.
pub fn fill32(client: &Client, h: &Handle, n: usize, bits: u32) {
    if n == 0 {
        return;
    }
    let (count, dim) = grid(n);
    fill_u32::launch(client, count, dim, arg(h, n), n as u32, bits);
}

// ---------------------------------------------------------------- exclusive prefix sum

#[cube(launch)]
fn scan_chunk_sums(input: &[u32], n: u32, chunk: u32, sums: &mut [u32]) {
    let t = ABSOLUTE_POS as u32;
    let start = t * chunk;
    if start < n {
        let end = u32::min(start + chunk, n);
        let mut s = 0u32;
        for i in start..end {
            s += input[i as usize];
        }
        sums[t as usize] = s;
    }
}

#[cube(launch)]
fn scan_chunks(input: &[u32], n: u32, chunk: u32, bases: &[u32], out: &mut [u32]) {
    let t = ABSOLUTE_POS as u32;
    let start = t * chunk;
    if start < n {
        let end = u32::min(start + chunk, n);
        let mut s = bases[t as usize];
        for i in start..end {
            let v = input[i as usize];
            out[i as usize] = s;
            s += v;
        }
    }
}

/// One cube of [`BLOCK_SCAN_UNITS`] units scans the whole (short) array and writes its total: each unit
/// sums a stripe of `stripe` values, the stripe sums are scanned in `partial` (Hillis–Steele, one round
/// per doubling, barriers in between), then each unit writes its stripe's prefix sums. Storage scratch
/// rather than workgroup memory, which cubecl-spirv 0.11.3 lowers wrongly on adapters without
/// `VK_KHR_workgroup_memory_explicit_layout` (docs/gpu.md): this kernel runs on every path. It replaced
/// a single unit walking up to 2048 values, ~50 µs a call on an H200 and 11 calls a render (one per
/// radix pass): 12 % of a late fit step's kernel time.
#[cube(launch)]
fn scan_block(
    input: &[u32],
    n: u32,
    stripe: u32,
    partial: &mut [u32],
    out: &mut [u32],
    total: &mut [u32],
) {
    let u = UNIT_POS;
    let start = u * stripe;
    let end = u32::min(start + stripe, n);
    let mut own = 0u32;
    for i in start..end {
        own += input[i as usize];
    }
    partial[u as usize] = own;
    sync_storage();
    let mut off = 1u32;
    for _ in 0..BLOCK_SCAN_ROUNDS {
        // Every unit reads the previous round's value before any unit writes this round's.
        let add = if u >= off {
            partial[(u - off) as usize]
        } else {
            0u32
        };
        sync_storage();
        partial[u as usize] += add;
        sync_storage();
        off *= 2;
    }
    let mut s = partial[u as usize] - own;
    for i in start..end {
        let v = input[i as usize];
        out[i as usize] = s;
        s += v;
    }
    if u == BLOCK_SCAN_UNITS - 1 {
        total[0] = partial[u as usize];
    }
}

/// Units of [`scan_block`]'s one cube (WebGPU's guaranteed minimum), and its rounds (log2).
const BLOCK_SCAN_UNITS: u32 = 256;
const BLOCK_SCAN_ROUNDS: u32 = BLOCK_SCAN_UNITS.trailing_zeros();

/// Exclusive prefix sum of the first `n` values of `input`: returns (sums, total) where `total` is a
/// one-element buffer. `input` is left unchanged.
pub fn exclusive_scan(client: &Client, input: &Handle, n: usize) -> (Handle, Handle) {
    let out = empty32(client, n);
    let total = empty32(client, 1);
    if n <= BLOCK_SCAN_MAX {
        let partial = empty32(client, BLOCK_SCAN_UNITS as usize);
        scan_block::launch(
            client,
            CubeCount::new_single(),
            CubeDim::new_1d(BLOCK_SCAN_UNITS),
            arg(input, n),
            n as u32,
            n.div_ceil(BLOCK_SCAN_UNITS as usize) as u32,
            arg(&partial, BLOCK_SCAN_UNITS as usize),
            arg(&out, n),
            arg(&total, 1),
        );
        return (out, total);
    }
    let chunk = chunk_len(n);
    let chunks = n.div_ceil(chunk);
    let sums = empty32(client, chunks);
    let (count, dim) = grid(chunks);
    scan_chunk_sums::launch(
        client,
        count.clone(),
        dim,
        arg(input, n),
        n as u32,
        chunk as u32,
        arg(&sums, chunks),
    );
    let (bases, total) = exclusive_scan(client, &sums, chunks);
    scan_chunks::launch(
        client,
        count,
        dim,
        arg(input, n),
        n as u32,
        chunk as u32,
        arg(&bases, chunks),
        arg(&out, n),
    );
    (out, total)
}

/// Elements per unit for an array of `n`: about 16k units, at least 32 elements each.
fn chunk_len(n: usize) -> usize {
    n.div_ceil(16 * 1024).max(32)
}

// ---------------------------------------------------------------- radix sort

/// Per-chunk digit histogram, stored digit-major (`counts[d * chunks + t]`) so that one exclusive scan
/// gives every chunk's first output slot for every digit in stable order.
#[cube(launch)]
fn radix_count(keys: &[u32], n: u32, chunk: u32, shift: u32, chunks: u32, counts: &mut [u32]) {
    let t = ABSOLUTE_POS as u32;
    if t < chunks {
        let mut hist = Array::<u32>::new(16usize);
        #[unroll]
        for d in 0..16usize {
            hist[d] = 0u32;
        }
        let start = t * chunk;
        let end = u32::min(start + chunk, n);
        for i in start..end {
            let d = (keys[i as usize] >> shift) & 15u32;
            hist[d as usize] += 1u32;
        }
        #[unroll]
        for d in 0..16usize {
            counts[d * chunks as usize + t as usize] = hist[d];
        }
    }
}

#[cube(launch)]
fn radix_scatter(
    keys: &[u32],
    vals: &[u32],
    n: u32,
    chunk: u32,
    shift: u32,
    chunks: u32,
    offsets: &[u32],
    keys_out: &mut [u32],
    vals_out: &mut [u32],
) {
    let t = ABSOLUTE_POS as u32;
    if t < chunks {
        let mut next = Array::<u32>::new(16usize);
        #[unroll]
        for d in 0..16usize {
            next[d] = offsets[d * chunks as usize + t as usize];
        }
        let start = t * chunk;
        let end = u32::min(start + chunk, n);
        for i in start..end {
            let k = keys[i as usize];
            let d = ((k >> shift) & 15u32) as usize;
            let slot = next[d] as usize;
            keys_out[slot] = k;
            vals_out[slot] = vals[i as usize];
            next[d] += 1u32;
        }
    }
}

/// Stable sort of `n` (key, value) pairs by the low `bits` bits of the keys (higher bits must be zero
/// or are ignored only if they do not vary). Returns the sorted keys and values; the inputs are reused
/// as scratch.
pub fn sort_pairs(
    client: &Client,
    keys: Handle,
    vals: Handle,
    n: usize,
    bits: u32,
) -> (Handle, Handle) {
    if n <= 1 || bits == 0 {
        return (keys, vals);
    }
    let chunk = chunk_len(n);
    let chunks = n.div_ceil(chunk);
    let counts = empty32(client, RADIX as usize * chunks);
    let (count, dim) = grid(chunks);
    let (mut k_in, mut v_in) = (keys, vals);
    let (mut k_out, mut v_out) = (empty32(client, n), empty32(client, n));
    for pass in 0..bits.div_ceil(RADIX_BITS) {
        let shift = pass * RADIX_BITS;
        radix_count::launch(
            client,
            count.clone(),
            dim,
            arg(&k_in, n),
            n as u32,
            chunk as u32,
            shift,
            chunks as u32,
            arg(&counts, RADIX as usize * chunks),
        );
        let (offsets, _) = exclusive_scan(client, &counts, RADIX as usize * chunks);
        radix_scatter::launch(
            client,
            count.clone(),
            dim,
            arg(&k_in, n),
            arg(&v_in, n),
            n as u32,
            chunk as u32,
            shift,
            chunks as u32,
            arg(&offsets, RADIX as usize * chunks),
            arg(&k_out, n),
            arg(&v_out, n),
        );
        std::mem::swap(&mut k_in, &mut k_out);
        std::mem::swap(&mut v_in, &mut v_out);
    }
    (k_in, v_in)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::testing::context_or_skip;

    fn lcg(seed: &mut u64) -> u32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 33) as u32
    }

    #[test]
    fn scan_matches_the_cpu_at_every_level() {
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let c = &ctx.client;
        let mut seed = 1;
        for n in [1usize, 7, 255, 256, 257, 1000, 2048, 2049, 100_000] {
            let v: Vec<u32> = (0..n).map(|_| lcg(&mut seed) % 10).collect();
            let (out, total) = exclusive_scan(c, &upload_u32(c, &v), n);
            let got = read_u32(c, &out, n).unwrap();
            let mut s = 0;
            for (i, x) in v.iter().enumerate() {
                assert_eq!(got[i], s, "n={n} i={i}");
                s += x;
            }
            assert_eq!(read_u32(c, &total, 1).unwrap()[0], s);
        }
    }

    #[test]
    fn radix_sort_is_stable() {
        let Some(ctx) = context_or_skip() else {
            return;
        };
        let c = &ctx.client;
        let mut seed = 5;
        for (n, bits) in [(5usize, 4u32), (3000, 10), (70_000, 32)] {
            let keys: Vec<u32> = (0..n)
                .map(|_| {
                    let k = lcg(&mut seed);
                    if bits == 32 {
                        k % 5000 // many ties
                    } else {
                        k % (1 << bits)
                    }
                })
                .collect();
            let vals: Vec<u32> = (0..n as u32).collect();
            let (k, v) = sort_pairs(c, upload_u32(c, &keys), upload_u32(c, &vals), n, bits);
            let (k, v) = (read_u32(c, &k, n).unwrap(), read_u32(c, &v, n).unwrap());
            let mut want: Vec<(u32, u32)> = keys.iter().copied().zip(vals).collect();
            want.sort_by_key(|&(k, _)| k); // stable
            let got: Vec<(u32, u32)> = k.into_iter().zip(v).collect();
            assert_eq!(got, want, "n={n} bits={bits}");
        }
    }
}
